//! SIGTERM: the process stops taking connections, lets the request in flight finish (a clip
//! whose remote reporter takes a second), lets the writer commit, and exits cleanly; a restart
//! finds the round.

use crate::support::*;
use std::time::Duration;
use vlmfuse_testkit::clips::h264_clip;
use vlmfuse_testkit::multipart::{content_type, multipart};
use vlmfuse_testkit::server::FakeOpenAi;
use vlmfuse_testkit_models::fixtures::clip_embedder_toml;

#[test]
fn sigterm_lets_the_request_in_flight_finish() {
    let tmp = tempfile::tempdir().unwrap();
    let fake = FakeOpenAi::start();
    let mut cfg = String::from("reporters = [\"videollama2\"]\n\n[media]\nframes = 2\n\n");
    cfg += &clip_embedder_toml(tmp.path());
    cfg += &fake.reporter_toml("videollama2", "frames");
    cfg += &fake.labeler_toml();
    let cfg_path = tmp.path().join("config.toml");
    std::fs::write(&cfg_path, &cfg).unwrap();
    let data = tmp.path().join("data");
    let args = ["--config", cfg_path.to_str().unwrap()];
    let mut srv = Server::start(&data, &args, &[]);
    let clip = h264_clip(tmp.path(), "a.mp4", "testsrc", 1.0);
    let body = multipart(&[("video", "a.mp4", &std::fs::read(&clip).unwrap())]);
    fake.slow_down(1000);

    let url = srv.url("/v1/infer");
    let inflight = std::thread::spawn(move || {
        read(
            client()
                .post(url)
                .header("content-type", content_type())
                .body(body)
                .send(),
        )
    });
    std::thread::sleep(Duration::from_millis(300));
    srv.sigterm();
    let r = inflight.join().unwrap();
    assert_eq!(r.status, 200, "{:?}", r.json());
    let status = srv.child.wait().unwrap();
    assert!(status.success(), "exit status {status}");
    drop(srv);

    fake.slow_down(0);
    let srv = Server::start(&data, &args, &[]);
    assert_eq!(
        srv.state()["rounds"],
        1,
        "the round answered at shutdown was kept"
    );
}
