//! Local HTTP servers for tests: a router on `127.0.0.1:0`, and a fake OpenAI-compatible server
//! (vLLM-shaped answers) for remote reporters and the OpenAI labeler.

use axum::extract::State;
use axum::http::StatusCode;
use axum::response::IntoResponse;
use axum::routing::post;
use axum::{Json, Router};
use serde_json::{json, Value};
use std::collections::{BTreeMap, HashSet};
use std::sync::{Arc, Mutex};

/// Serves `app` on an ephemeral loopback port from the current runtime; returns its base URL.
pub async fn serve_local(app: Router) -> String {
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0")
        .await
        .expect("bind 127.0.0.1:0");
    let url = format!("http://{}", listener.local_addr().expect("local addr"));
    tokio::spawn(async move { axum::serve(listener, app).await });
    url
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
    /// Milliseconds each answer waits (a slow backend).
    pub delay_ms: u64,
    /// Requests seen per model.
    pub calls: BTreeMap<String, usize>,
    /// The last request body per model (what a client sent: prompt, options).
    pub last_request: BTreeMap<String, Value>,
}

/// An OpenAI-compatible server on 127.0.0.1:0 with its own runtime (usable from sync and async
/// tests alike), answering like vLLM: driving text for every reporter model, `{"labels": [...]}`
/// for [`LABELER_MODEL`], 500 for models marked dead.
pub struct FakeOpenAi {
    pub url: String,
    pub state: Arc<Mutex<FakeState>>,
    /// `Some` until dropped; shut down in the background so that dropping is fine inside an
    /// async test too.
    rt: Option<tokio::runtime::Runtime>,
}

impl Drop for FakeOpenAi {
    fn drop(&mut self) {
        if let Some(rt) = self.rt.take() {
            rt.shutdown_background();
        }
    }
}

impl FakeOpenAi {
    pub fn start() -> FakeOpenAi {
        let rt = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(1)
            .enable_all()
            .build()
            .expect("runtime");
        let state = Arc::new(Mutex::new(FakeState::default()));
        let app = Router::new()
            .route("/v1/chat/completions", post(chat))
            .route("/v1/models", axum::routing::get(models))
            .with_state(state.clone());
        // Started from another thread: `block_on` is refused inside an async test's runtime.
        let url = std::thread::scope(|s| {
            s.spawn(|| rt.block_on(serve_local(app)))
                .join()
                .expect("fake server thread")
        });
        FakeOpenAi {
            url,
            state,
            rt: Some(rt),
        }
    }

    pub fn kill(&self, model: &str) {
        self.state.lock().unwrap().dead.insert(model.into());
    }

    /// Every answer from now on waits `ms` milliseconds.
    pub fn slow_down(&self, ms: u64) {
        self.state.lock().unwrap().delay_ms = ms;
    }

    /// The last request body the server got for `model`.
    pub fn last_request(&self, model: &str) -> Option<Value> {
        self.state.lock().unwrap().last_request.get(model).cloned()
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

    /// A remote reporter section served by this server under `model = "{name}-7b"`.
    pub fn reporter_toml(&self, name: &str, mode: &str) -> String {
        format!(
            "[[reporter]]\nkind = \"openai\"\nname = \"{name}\"\nbase_url = \"{}\"\nmodel = \"{name}-7b\"\n\
             mode = \"{mode}\"\nretries = 0\ntimeout_s = 20.0\nround_timeout_s = 30.0\n\n",
            self.url
        )
    }

    /// An `[labeler]` section for the OpenAI labeler served by this server.
    pub fn labeler_toml(&self) -> String {
        format!(
            "[labeler]\nkind = \"openai\"\nbase_url = \"{}\"\nmodel = \"{LABELER_MODEL}\"\ntimeout_s = 20.0\n\n",
            self.url
        )
    }
}

/// `GET /v1/models`, what a health probe asks: the models seen so far, like vLLM's listing.
async fn models(State(st): State<Arc<Mutex<FakeState>>>) -> impl IntoResponse {
    let s = st.lock().unwrap();
    let data: Vec<Value> = s
        .calls
        .keys()
        .map(|m| json!({"id": m, "object": "model"}))
        .collect();
    Json(json!({"object": "list", "data": data}))
}

async fn chat(
    State(st): State<Arc<Mutex<FakeState>>>,
    Json(body): Json<Value>,
) -> impl IntoResponse {
    let model = body["model"].as_str().unwrap_or("").to_string();
    // The request shape a vLLM would need: messages with the prompt (and media for reporters).
    let ok_shape = body["messages"].as_array().is_some_and(|m| !m.is_empty());
    let (dead, delay) = {
        let mut s = st.lock().unwrap();
        *s.calls.entry(model.clone()).or_default() += 1;
        s.last_request.insert(model.clone(), body.clone());
        (s.dead.contains(&model), s.delay_ms)
    };
    if delay > 0 {
        tokio::time::sleep(std::time::Duration::from_millis(delay)).await;
    }
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
