//! The service in-process: `app(state)` driven with `oneshot` requests (no socket, no child
//! process), a response type that shows exactly what the router answered, and the configs the
//! clip tests use.
#![allow(dead_code)]

use axum::body::Body;
use axum::http::Request;
use axum::Router;
use serde_json::Value;
use std::path::{Path, PathBuf};
use tower::ServiceExt;
use vlmfuse::{app, AppState, Config};
use vlmfuse_testkit::multipart::{content_type, multipart};
pub use vlmfuse_testkit::resp::Resp;

pub struct TestApp {
    pub state: AppState,
    router: Router,
    pub data_dir: PathBuf,
}

impl TestApp {
    /// A service over `cfg` with its database in `data_dir`.
    pub async fn start(data_dir: &Path, mut cfg: Config) -> TestApp {
        cfg.server.data_dir = data_dir.to_path_buf();
        cfg.validate().unwrap();
        let started = vlmfuse::serve::build(cfg).await.expect("service starts");
        TestApp {
            router: app(started.state.clone()),
            state: started.state,
            data_dir: data_dir.to_path_buf(),
        }
    }

    /// A service over a TOML config (written as an operator would), database under `dir/data`.
    pub async fn from_toml(dir: &Path, toml: &str) -> TestApp {
        let cfg = Config::from_toml(toml).unwrap_or_else(|e| panic!("{e:#}\n{toml}"));
        TestApp::start(&dir.join("data"), cfg).await
    }

    pub async fn request(
        &self,
        method: &str,
        path: &str,
        headers: &[(&str, &str)],
        body: Vec<u8>,
    ) -> Resp {
        let mut b = Request::builder().method(method).uri(path);
        for (k, v) in headers {
            b = b.header(*k, *v);
        }
        let resp = self
            .router
            .clone()
            .oneshot(b.body(Body::from(body)).unwrap())
            .await
            .unwrap();
        let status = resp.status().as_u16();
        let headers = resp
            .headers()
            .iter()
            .map(|(k, v)| (k.to_string(), v.to_str().unwrap_or("").to_string()))
            .collect();
        let body = axum::body::to_bytes(resp.into_body(), usize::MAX)
            .await
            .unwrap()
            .to_vec();
        Resp {
            status,
            headers,
            body,
        }
    }

    /// The router itself, for requests `request` cannot build (streamed bodies).
    pub fn router(&self) -> Router {
        self.router.clone()
    }

    pub async fn get(&self, path: &str) -> Resp {
        self.request("GET", path, &[], Vec::new()).await
    }

    pub async fn post(&self, path: &str, body: &Value) -> Resp {
        self.request(
            "POST",
            path,
            &[("content-type", "application/json")],
            serde_json::to_vec(body).unwrap(),
        )
        .await
    }

    pub async fn state(&self) -> Value {
        let r = self.get("/v1/state").await;
        assert_eq!(r.status, 200);
        r.json()
    }

    pub async fn post_multipart(&self, body: Vec<u8>) -> Resp {
        let ct = content_type();
        self.request("POST", "/v1/infer", &[("content-type", ct.as_str())], body)
            .await
    }

    pub async fn post_clip(&self, path: &Path) -> Resp {
        let data = std::fs::read(path).unwrap();
        let name = path.file_name().unwrap().to_str().unwrap();
        self.post_multipart(multipart(&[("video", name, &data)]))
            .await
    }
}
