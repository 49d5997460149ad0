//! `OpenAiReporter` against a local fake OpenAI-compatible server that checks request shapes.

use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use axum::extract::State;
use axum::http::{HeaderMap, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::routing::post;
use axum::{Json, Router};
use base64::Engine as _;
use serde_json::{json, Value};
use vlmfuse_models::reporter::{FrameFormat, OpenAiMode};
use vlmfuse_models::{
    ClipInput, ClipMeta, Frame, OpenAiReporter, OpenAiReporterConfig, Reporter, DEFAULT_PROMPT,
};
use vlmfuse_testkit::server::serve_local;

#[derive(Clone)]
struct Reply {
    status: u16,
    headers: Vec<(&'static str, String)>,
    body: Value,
    delay: Duration,
}

fn ok(text: &str) -> Reply {
    Reply {
        status: 200,
        headers: vec![],
        // Shaped like a vLLM response.
        body: json!({
            "id": "chatcmpl-123", "object": "chat.completion", "created": 1,
            "model": "served-model",
            "choices": [{"index": 0, "message": {"role": "assistant", "content": text,
                "reasoning_content": null, "tool_calls": []},
                "logprobs": null, "finish_reason": "stop", "stop_reason": null}],
            "usage": {"prompt_tokens": 10, "total_tokens": 20, "completion_tokens": 10}
        }),
        delay: Duration::ZERO,
    }
}

fn status(code: u16) -> Reply {
    Reply {
        status: code,
        headers: vec![],
        body: json!({"object": "error", "message": "overloaded", "code": code}),
        delay: Duration::ZERO,
    }
}

type Script = Arc<dyn Fn(usize) -> Reply + Send + Sync>;

#[derive(Clone)]
struct Fake {
    seen: Arc<Mutex<Vec<(HeaderMap, Value)>>>,
    script: Script,
}

async fn handler(State(f): State<Fake>, headers: HeaderMap, Json(body): Json<Value>) -> Response {
    let n = {
        let mut s = f.seen.lock().unwrap();
        s.push((headers, body));
        s.len() - 1
    };
    let r = (f.script)(n);
    tokio::time::sleep(r.delay).await;
    let mut resp = (StatusCode::from_u16(r.status).unwrap(), Json(r.body)).into_response();
    for (k, v) in r.headers {
        resp.headers_mut().insert(k, v.parse().unwrap());
    }
    resp
}

/// Starts the fake on 127.0.0.1:0; returns its base URL and the requests it received.
async fn fake(script: impl Fn(usize) -> Reply + Send + Sync + 'static) -> (String, Fake) {
    let f = Fake {
        seen: Arc::default(),
        script: Arc::new(script),
    };
    let app = Router::new()
        .route("/v1/chat/completions", post(handler))
        .with_state(f.clone());
    (serve_local(app).await, f)
}

fn cfg(base_url: &str) -> OpenAiReporterConfig {
    OpenAiReporterConfig {
        base_url: base_url.into(),
        model: "Qwen/Qwen2.5-VL-7B-Instruct".into(),
        backoff_initial_ms: 10,
        backoff_max_ms: 2_000,
        timeout_s: 5.0,
        ..Default::default()
    }
}

fn clip(dir: &std::path::Path) -> ClipInput {
    let path = dir.join("clip.mp4");
    std::fs::write(&path, b"\x00\x00\x00\x18ftypmp42 not really a video").unwrap();
    let frames: Vec<Frame> = (0..3u8)
        .map(|k| Frame {
            width: 4,
            height: 3,
            rgb: (0..36u8)
                .map(|i| i.wrapping_mul(7).wrapping_add(k * 50))
                .collect(),
            pts_s: k as f64,
        })
        .collect();
    ClipInput {
        path,
        frames: frames.into(),
        meta: ClipMeta::default(),
    }
}

fn b64(s: &str) -> Vec<u8> {
    base64::engine::general_purpose::STANDARD.decode(s).unwrap()
}

#[tokio::test]
async fn video_url_mode_sends_inline_video_with_bearer() {
    // Unique name: no other test reads it, so setting it cannot race.
    std::env::set_var("VLMFUSE_TEST_OPENAI_KEY_1", "sk-test-123");
    let (url, f) = fake(|_| ok("Scene: a road.")).await;
    let tmp = tempfile::tempdir().unwrap();
    let c = clip(tmp.path());
    let r = OpenAiReporter::new(OpenAiReporterConfig {
        api_key_env: Some("VLMFUSE_TEST_OPENAI_KEY_1".into()),
        max_tokens: 77,
        ..cfg(&url)
    })
    .unwrap();
    assert_eq!(r.name(), "Qwen/Qwen2.5-VL-7B-Instruct");
    let out = r.run(&c).await.unwrap();
    assert_eq!(out.text, "Scene: a road.");
    assert_eq!(out.model, "served-model");
    assert!(out.latency_ms > 0.0);

    let seen = f.seen.lock().unwrap();
    assert_eq!(seen.len(), 1);
    let (h, body) = &seen[0];
    assert_eq!(h["authorization"], "Bearer sk-test-123");
    assert_eq!(body["model"], "Qwen/Qwen2.5-VL-7B-Instruct");
    assert_eq!(body["max_tokens"], 77);
    assert_eq!(body["temperature"], 0.0);
    let msgs = body["messages"].as_array().unwrap();
    assert_eq!(msgs.len(), 1);
    assert_eq!(msgs[0]["role"], "user");
    let parts = msgs[0]["content"].as_array().unwrap();
    assert_eq!(parts.len(), 2);
    assert_eq!(parts[0]["type"], "video_url");
    let u = parts[0]["video_url"]["url"].as_str().unwrap();
    let data = u.strip_prefix("data:video/mp4;base64,").expect(u);
    assert_eq!(b64(data), std::fs::read(&c.path).unwrap());
    assert_eq!(parts[1]["type"], "text");
    assert_eq!(parts[1]["text"], DEFAULT_PROMPT);
}

#[tokio::test]
async fn video_url_template_sends_a_reference_not_the_bytes() {
    let (url, f) = fake(|_| ok("x")).await;
    let tmp = tempfile::tempdir().unwrap();
    let c = clip(tmp.path());
    let r = OpenAiReporter::new(OpenAiReporterConfig {
        video_url_template: Some("file://{path}".into()),
        prompt: "custom prompt".into(),
        ..cfg(&format!("{url}/v1"))
    })
    .unwrap();
    r.run(&c).await.unwrap();
    let seen = f.seen.lock().unwrap();
    let (h, body) = &seen[0];
    assert!(
        h.get("authorization").is_none(),
        "no key configured, no header"
    );
    let parts = &body["messages"][0]["content"];
    assert_eq!(
        parts[0]["video_url"]["url"],
        format!("file://{}", c.path.display())
    );
    assert_eq!(parts[1]["text"], "custom prompt");
}

#[tokio::test]
async fn frames_mode_sends_one_image_part_per_frame() {
    let (url, f) = fake(|_| ok("Manoeuvres: slow down.")).await;
    let tmp = tempfile::tempdir().unwrap();
    let c = clip(tmp.path());
    let mut extra = serde_json::Map::new();
    extra.insert("top_p".into(), json!(0.9));
    let r = OpenAiReporter::new(OpenAiReporterConfig {
        name: Some("llava-frames".into()),
        mode: OpenAiMode::Frames,
        frame_format: FrameFormat::Png,
        system_prompt: Some("You are a driving expert.".into()),
        extra_body: Some(extra),
        ..cfg(&url)
    })
    .unwrap();
    assert_eq!(r.name(), "llava-frames");
    let out = r.run(&c).await.unwrap();
    assert_eq!(out.text, "Manoeuvres: slow down.");

    let seen = f.seen.lock().unwrap();
    let body = &seen[0].1;
    assert_eq!(body["top_p"], 0.9);
    let msgs = body["messages"].as_array().unwrap();
    assert_eq!(msgs[0]["role"], "system");
    assert_eq!(msgs[1]["role"], "user");
    let parts = msgs[1]["content"].as_array().unwrap();
    assert_eq!(parts.len(), 4, "3 frames + text");
    for (k, p) in parts[..3].iter().enumerate() {
        assert_eq!(p["type"], "image_url");
        let u = p["image_url"]["url"].as_str().unwrap();
        let png = b64(u.strip_prefix("data:image/png;base64,").expect(u));
        let img = image::load_from_memory(&png).unwrap().to_rgb8();
        assert_eq!(img.dimensions(), (4, 3));
        assert_eq!(img.into_raw(), c.frames[k].rgb, "frame {k} pixels");
    }
    assert_eq!(parts[3]["type"], "text");
}

#[tokio::test]
async fn retries_after_503_then_succeeds() {
    let (url, f) = fake(|n| if n == 0 { status(503) } else { ok("fine") }).await;
    let tmp = tempfile::tempdir().unwrap();
    let r = OpenAiReporter::new(OpenAiReporterConfig {
        retries: 2,
        ..cfg(&url)
    })
    .unwrap();
    let out = r.run(&clip(tmp.path())).await.unwrap();
    assert_eq!(out.text, "fine");
    assert_eq!(f.seen.lock().unwrap().len(), 2);
}

#[tokio::test]
async fn honours_retry_after_on_429() {
    let (url, f) = fake(|n| {
        if n == 0 {
            let mut r = status(429);
            r.headers.push(("retry-after", "1".into()));
            r
        } else {
            ok("after wait")
        }
    })
    .await;
    let tmp = tempfile::tempdir().unwrap();
    let r = OpenAiReporter::new(OpenAiReporterConfig {
        retries: 1,
        ..cfg(&url)
    })
    .unwrap();
    let t0 = Instant::now();
    r.run(&clip(tmp.path())).await.unwrap();
    let el = t0.elapsed();
    assert!(
        el >= Duration::from_millis(950),
        "did not wait for Retry-After: {el:?}"
    );
    assert!(el < Duration::from_millis(1900), "{el:?}");
    assert_eq!(f.seen.lock().unwrap().len(), 2);
}

#[tokio::test]
async fn gives_up_after_retries_and_names_the_status() {
    let (url, f) = fake(|_| status(500)).await;
    let tmp = tempfile::tempdir().unwrap();
    let r = OpenAiReporter::new(OpenAiReporterConfig {
        retries: 2,
        ..cfg(&url)
    })
    .unwrap();
    let e = r.run(&clip(tmp.path())).await.unwrap_err();
    assert_eq!(e.kind(), "remote");
    let msg = e.to_string();
    assert!(msg.contains("500") && msg.contains("3 attempt"), "{msg}");
    assert_eq!(f.seen.lock().unwrap().len(), 3);
}

#[tokio::test]
async fn client_errors_are_not_retried() {
    let (url, f) = fake(|_| status(400)).await;
    let tmp = tempfile::tempdir().unwrap();
    let r = OpenAiReporter::new(OpenAiReporterConfig {
        retries: 3,
        ..cfg(&url)
    })
    .unwrap();
    let e = r.run(&clip(tmp.path())).await.unwrap_err();
    assert!(e.to_string().contains("400"), "{e}");
    assert_eq!(f.seen.lock().unwrap().len(), 1);
}

#[tokio::test]
async fn slow_server_times_out() {
    let (url, f) = fake(|_| Reply {
        delay: Duration::from_secs(3),
        ..ok("too late")
    })
    .await;
    let tmp = tempfile::tempdir().unwrap();
    let r = OpenAiReporter::new(OpenAiReporterConfig {
        timeout_s: 0.3,
        retries: 1,
        ..cfg(&url)
    })
    .unwrap();
    let t0 = Instant::now();
    let e = r.run(&clip(tmp.path())).await.unwrap_err();
    let el = t0.elapsed();
    assert_eq!(e.kind(), "timeout", "{e}");
    assert_eq!(
        f.seen.lock().unwrap().len(),
        2,
        "one retry after the first timeout"
    );
    assert!(el < Duration::from_millis(1500), "{el:?}");
}

#[tokio::test]
async fn unreachable_server_is_a_remote_error() {
    let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let addr = listener.local_addr().unwrap();
    drop(listener);
    let tmp = tempfile::tempdir().unwrap();
    let r = OpenAiReporter::new(OpenAiReporterConfig {
        retries: 0,
        ..cfg(&format!("http://{addr}"))
    })
    .unwrap();
    let e = r.run(&clip(tmp.path())).await.unwrap_err();
    assert_eq!(e.kind(), "remote", "{e}");
    assert!(e.to_string().contains(&addr.to_string()), "{e}");
}

/// A refused connection is final: no backoff and retry (the server is not there).
#[tokio::test]
async fn a_refused_connection_fails_fast() {
    let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let addr = listener.local_addr().unwrap();
    drop(listener);
    let tmp = tempfile::tempdir().unwrap();
    let r = OpenAiReporter::new(OpenAiReporterConfig {
        retries: 2,
        backoff_initial_ms: 500,
        ..cfg(&format!("http://{addr}"))
    })
    .unwrap();
    let t = Instant::now();
    let e = r.run(&clip(tmp.path())).await.unwrap_err();
    let el = t.elapsed();
    assert!(el < Duration::from_millis(300), "took {el:?}: {e}");
    assert!(e.to_string().contains("1 attempt"), "{e}");
}

/// An upstream answer larger than `max_response_bytes` is refused with a clear error, not read
/// whole into memory.
#[tokio::test]
async fn an_oversized_answer_is_refused() {
    let big = "x".repeat(300_000);
    let (url, _f) = fake(move |_| ok(&big)).await;
    let tmp = tempfile::tempdir().unwrap();
    let r = OpenAiReporter::new(OpenAiReporterConfig {
        max_response_bytes: 100_000,
        ..cfg(&url)
    })
    .unwrap();
    let e = r.run(&clip(tmp.path())).await.unwrap_err();
    let s = e.to_string();
    assert!(
        s.contains("100000") && s.contains("max_response_bytes"),
        "{s}"
    );
    // Under the cap it is read.
    let r = OpenAiReporter::new(OpenAiReporterConfig {
        max_response_bytes: 1_000_000,
        ..cfg(&url)
    })
    .unwrap();
    assert_eq!(r.run(&clip(tmp.path())).await.unwrap().text.len(), 300_000);
}
