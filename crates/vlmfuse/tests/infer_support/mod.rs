//! Shared by the `infer_*` tests: clips made with the `ffmpeg` CLI, multipart bodies, tiny model
//! fixtures, and a fake OpenAI-compatible server (vLLM-shaped answers) for remote reporters and
//! the OpenAI labeler.
#![allow(dead_code)]

use axum::extract::State;
use axum::http::StatusCode;
use axum::response::IntoResponse;
use axum::routing::post;
use axum::{Json, Router};
use serde_json::{json, Value};
use std::collections::{BTreeMap, HashSet};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::{Arc, Mutex};

use crate::service_support::{request, Resp, Server};

/// Runs the `ffmpeg` CLI quietly; panics with its stderr on failure.
pub fn ffmpeg(args: &[&str], out: &Path) -> PathBuf {
    let o = Command::new("ffmpeg")
        .args(["-hide_banner", "-loglevel", "error", "-y"])
        .args(args)
        .arg(out)
        .output()
        .expect("the ffmpeg CLI is needed to make test clips");
    assert!(
        o.status.success(),
        "ffmpeg {args:?}: {}",
        String::from_utf8_lossy(&o.stderr)
    );
    out.to_path_buf()
}

/// A short H.264 mp4 of an lavfi source (`testsrc`, `mandelbrot`, ...).
pub fn h264_clip(dir: &Path, name: &str, source: &str, secs: f64) -> PathBuf {
    ffmpeg(
        &[
            "-f",
            "lavfi",
            "-i",
            &format!("{source}=size=160x120:rate=10"),
            "-t",
            &secs.to_string(),
            "-c:v",
            "libx264",
            "-pix_fmt",
            "yuv420p",
        ],
        &dir.join(name),
    )
}

pub const BOUNDARY: &str = "vlmfuse-test-boundary-7MA4YWxk";

/// `multipart/form-data` with one part per `(part name, file name, bytes)`.
pub fn multipart(parts: &[(&str, &str, &[u8])]) -> Vec<u8> {
    let mut b = Vec::new();
    for (name, file, data) in parts {
        b.extend_from_slice(
            format!(
                "--{BOUNDARY}\r\nContent-Disposition: form-data; name=\"{name}\"; \
                 filename=\"{file}\"\r\nContent-Type: application/octet-stream\r\n\r\n"
            )
            .as_bytes(),
        );
        b.extend_from_slice(data);
        b.extend_from_slice(b"\r\n");
    }
    b.extend_from_slice(format!("--{BOUNDARY}--\r\n").as_bytes());
    b
}

pub fn post_multipart(srv: &Server, body: &[u8]) -> Resp {
    let ct = format!("multipart/form-data; boundary={BOUNDARY}");
    request(
        &srv.addr,
        "POST",
        "/v1/infer",
        &[("content-type", ct.as_str())],
        Some(body),
    )
    .expect("request")
}

pub fn post_clip(srv: &Server, path: &Path) -> Resp {
    let data = std::fs::read(path).unwrap();
    let name = path.file_name().unwrap().to_str().unwrap();
    post_multipart(srv, &multipart(&[("video", name, &data)]))
}

/// Text a driving VLM would write, following the three-step prompt.
pub const DRIVING_TEXT: &str = "Scene: an urban road at night, wet after rain, with a red traffic \
light ahead and a pedestrian waiting at the crossing.\nManoeuvres: slow down and stop at the \
light.\nRationale: the light is red and the road is wet, so braking early is safe.";

/// What the fake labeler LLM answers for every text.
pub const LABELER_LABELS: [&str; 3] = ["brake", "stop", "traffic_light_ahead"];
pub const LABELER_MODEL: &str = "fake-labeler";

#[derive(Default)]
pub struct FakeState {
    /// Models that answer 500 (a dead backend).
    pub dead: HashSet<String>,
    /// Requests seen per model.
    pub calls: BTreeMap<String, usize>,
}

/// An OpenAI-compatible server on 127.0.0.1:0, answering like vLLM: driving text for every
/// reporter model, `{"labels": [...]}` for [`LABELER_MODEL`], 500 for models marked dead.
pub struct FakeOpenAi {
    pub url: String,
    pub state: Arc<Mutex<FakeState>>,
    _rt: tokio::runtime::Runtime,
}

impl FakeOpenAi {
    pub fn start() -> FakeOpenAi {
        let rt = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(1)
            .enable_all()
            .build()
            .unwrap();
        let state = Arc::new(Mutex::new(FakeState::default()));
        let app = Router::new()
            .route("/v1/chat/completions", post(chat))
            .with_state(state.clone());
        let listener = rt
            .block_on(tokio::net::TcpListener::bind("127.0.0.1:0"))
            .unwrap();
        let url = format!("http://{}", listener.local_addr().unwrap());
        rt.spawn(async move { axum::serve(listener, app).await });
        FakeOpenAi {
            url,
            state,
            _rt: rt,
        }
    }

    pub fn kill(&self, model: &str) {
        self.state.lock().unwrap().dead.insert(model.into());
    }

    pub fn calls(&self, model: &str) -> usize {
        self.state
            .lock()
            .unwrap()
            .calls
            .get(model)
            .copied()
            .unwrap_or(0)
    }
}

async fn chat(
    State(st): State<Arc<Mutex<FakeState>>>,
    Json(body): Json<Value>,
) -> impl IntoResponse {
    let model = body["model"].as_str().unwrap_or("").to_string();
    // The request shape a vLLM would need: messages with the prompt (and media for reporters).
    let ok_shape = body["messages"].as_array().is_some_and(|m| !m.is_empty());
    let dead = {
        let mut s = st.lock().unwrap();
        *s.calls.entry(model.clone()).or_default() += 1;
        s.dead.contains(&model)
    };
    if !ok_shape {
        return (
            StatusCode::BAD_REQUEST,
            Json(json!({"error": "no messages"})),
        );
    }
    if dead {
        return (
            StatusCode::INTERNAL_SERVER_ERROR,
            Json(json!({"object": "error", "message": "engine dead", "code": 500})),
        );
    }
    let content = if model == LABELER_MODEL {
        json!({ "labels": LABELER_LABELS }).to_string()
    } else {
        DRIVING_TEXT.to_string()
    };
    (
        StatusCode::OK,
        Json(json!({
            "id": "chatcmpl-1", "object": "chat.completion", "created": 1, "model": model,
            "choices": [{"index": 0, "message": {"role": "assistant", "content": content,
                "reasoning_content": null, "tool_calls": []},
                "logprobs": null, "finish_reason": "stop", "stop_reason": null}],
            "usage": {"prompt_tokens": 10, "total_tokens": 20, "completion_tokens": 10}
        })),
    )
}

/// A remote reporter section served by `fake` under `model`.
pub fn openai_reporter(name: &str, fake: &FakeOpenAi, mode: &str) -> String {
    format!(
        "[[reporter]]\nkind = \"openai\"\nname = \"{name}\"\nbase_url = \"{}\"\nmodel = \"{name}-7b\"\n\
         mode = \"{mode}\"\nretries = 0\ntimeout_s = 20.0\nround_timeout_s = 30.0\n\n",
        fake.url
    )
}

pub fn openai_labeler(fake: &FakeOpenAi) -> String {
    format!(
        "[labeler]\nkind = \"openai\"\nbase_url = \"{}\"\nmodel = \"{LABELER_MODEL}\"\ntimeout_s = 20.0\n\n",
        fake.url
    )
}

/// Writes a tiny random CLIP under `dir` and returns its `[embedder]` section.
pub fn tiny_clip_embedder(dir: &Path) -> String {
    let d = dir.join("clip");
    vlmfuse_models::fixtures::TinyClip::default()
        .write(&d, 7)
        .unwrap();
    format!(
        "[embedder]\nweights = {{ path = {:?} }}\ndevice = \"cpu\"\n\n",
        d
    )
}

/// Writes a tiny random Qwen3-VL under `dir` and returns its `[[reporter]]` section.
pub fn tiny_qwen_reporter(dir: &Path, name: &str) -> String {
    let d = dir.join("qwen");
    vlmfuse_models::fixtures::TinyQwen3Vl::default()
        .write(&d, 11)
        .unwrap();
    format!(
        "[[reporter]]\nkind = \"candle\"\nname = \"{name}\"\nweights = {{ path = {:?} }}\n\
         device = \"cpu\"\nmax_new_tokens = 6\nframes = 2\nmin_pixels = 256\nmax_pixels = 1024\n\
         round_timeout_s = 60.0\n\n",
        d
    )
}

/// Starts the server on `config` (TOML text written into `dir`).
pub fn start(dir: &Path, config: &str) -> Server {
    let cfg = dir.join("config.toml");
    std::fs::write(&cfg, config).unwrap();
    Server::start(&dir.join("data"), &["--config", cfg.to_str().unwrap()], &[])
}
