//! Issue 10's open half, in-process: a huge multipart preamble is refused at once; async
//! routes never block a runtime thread on the engine lock; idempotent retries; the context
//! dimension of a configured embedder; per-component readiness.

use crate::support::TestApp;
use axum::body::Body;
use axum::http::Request;
use serde_json::Value;
use std::time::{Duration, Instant};
use tower::ServiceExt;
use vlmfuse_testkit::fixtures::clip_embedder_toml;
use vlmfuse_testkit::multipart::{content_type, multipart, BOUNDARY};
use vlmfuse_testkit::server::FakeOpenAi;

fn infer_config(dir: &std::path::Path, fake: &FakeOpenAi) -> String {
    let mut c = String::from(
        "reporters = [\"videollama2\", \"videollava\"]\n\n[media]\nframes = 4\n\
         max_bytes = 1000000\nmax_clips = 2\n\n",
    );
    c += &clip_embedder_toml(dir);
    c += &fake.reporter_toml("videollama2", "frames");
    c += &fake.reporter_toml("videollava", "video_url");
    c += &fake.labeler_toml();
    c
}

/// 16 MiB of junk before the first boundary, streamed in 64 KiB chunks as a socket delivers
/// it: refused with 400 `multipart_preamble_too_long` in well under a second (the whole
/// preamble used to be buffered and rescanned: seconds, and its size in RSS).
#[tokio::test(flavor = "multi_thread")]
async fn a_huge_multipart_preamble_is_refused_at_once() {
    let tmp = tempfile::tempdir().unwrap();
    let fake = FakeOpenAi::start();
    let srv = TestApp::from_toml(tmp.path(), &infer_config(tmp.path(), &fake)).await;
    let clip = vlmfuse_testkit::clips::h264_clip(tmp.path(), "a.mp4", "testsrc", 1.0);
    let data = std::fs::read(&clip).unwrap();

    // A short preamble (RFC 2046 allows one) is still fine.
    let mut ok = b"this is a preamble, ignore it\r\n".to_vec();
    ok.extend(multipart(&[("video", "a.mp4", &data)]));
    let r = srv.post_multipart(ok).await;
    assert_eq!(r.status, 200, "{}", r.json());

    let chunk = vec![b'x'; 64 * 1024];
    let mut parts: Vec<Result<Vec<u8>, std::io::Error>> =
        (0..256).map(|_| Ok(chunk.clone())).collect();
    parts.push(Ok(multipart(&[("video", "a.mp4", &data)])));
    let body = Body::from_stream(futures::stream::iter(parts));
    let req = Request::builder()
        .method("POST")
        .uri("/v1/infer")
        .header("content-type", content_type())
        .body(body)
        .unwrap();
    let t = Instant::now();
    let resp = srv.router().oneshot(req).await.unwrap();
    let status = resp.status().as_u16();
    let v: Value = serde_json::from_slice(
        &axum::body::to_bytes(resp.into_body(), usize::MAX)
            .await
            .unwrap(),
    )
    .unwrap();
    let took = t.elapsed();
    assert_eq!(status, 400, "{v}");
    assert_eq!(v["kind"], "multipart_preamble_too_long", "{v}");
    assert!(
        v["error"].as_str().unwrap().contains(BOUNDARY)
            || v["error"].as_str().unwrap().contains("boundary"),
        "{v}"
    );
    assert!(took < Duration::from_millis(500), "took {took:?}");
    assert_eq!(
        srv.state().await["rounds"],
        1,
        "nothing stored for the refused upload"
    );
}
