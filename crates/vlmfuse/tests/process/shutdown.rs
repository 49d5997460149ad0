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

/// A clean shutdown snapshots the final state (below `snapshot_every`), so the next start loads
/// it and replays nothing; a start with the snapshot directory gone replays everything and
/// reaches the same state.
#[test]
fn sigterm_leaves_a_snapshot_of_the_final_state() {
    use serde_json::json;
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("data");
    let args = ["--reporters", "a,b"];
    let mut srv = Server::start(&dir, &args, &[]);
    for i in 0..12 {
        let x = i as f64;
        let r = srv.post(
            "/v1/fuse",
            &json!({"context": [1.0, x, 0.5], "reports": {"a": ["brake"], "b": []}}),
        );
        assert_eq!(r.status, 200);
        if i % 2 == 0 {
            let id = r.json()["round_id"].clone();
            let fb = srv.post(
                "/v1/feedback",
                &json!({"round_id": id, "labels": ["brake"]}),
            );
            assert_eq!(fb.status, 200);
        }
    }
    let before = srv.state();
    srv.sigterm();
    let status = srv.child.wait().unwrap();
    assert!(status.success(), "{status:?}");
    let snaps: Vec<_> = std::fs::read_dir(dir.join("snapshots"))
        .unwrap()
        .filter_map(|e| e.ok())
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .collect();
    assert_eq!(snaps, ["snapshot-000000000006-000000000012.bin"]);

    let srv = Server::start(&dir, &args, &[("RUST_LOG", "info")]);
    assert_eq!(srv.state(), before);
    let log = std::fs::read_to_string(dir.join("server.log")).unwrap();
    // Without the terminal colours around the field names.
    let mut plain = String::new();
    let mut chars = log.chars();
    while let Some(c) = chars.next() {
        if c == '\u{1b}' {
            for d in chars.by_ref() {
                if d == 'm' {
                    break;
                }
            }
        } else {
            plain.push(c);
        }
    }
    assert!(
        plain.contains("tail_rounds=0 tail_feedback=0"),
        "the start replayed events: {log}"
    );
    drop(srv);
    std::fs::remove_dir_all(dir.join("snapshots")).unwrap();
    // A start that replayed at least `snapshot_every` events snapshots them at once (the writer
    // wakes once a second), without waiting for new ones.
    let srv = Server::start(&dir, &["--reporters", "a,b", "--snapshot-every", "5"], &[]);
    assert_eq!(srv.state(), before, "the full replay reaches another state");
    let want = dir.join("snapshots/snapshot-000000000006-000000000012.bin");
    let deadline = std::time::Instant::now() + Duration::from_secs(20);
    while !want.exists() {
        assert!(
            std::time::Instant::now() < deadline,
            "no snapshot after the full replay"
        );
        std::thread::sleep(Duration::from_millis(50));
    }
    // Counted by the service's recorder, from the snapshot thread.
    let deadline = std::time::Instant::now() + Duration::from_secs(10);
    loop {
        let m = String::from_utf8_lossy(&srv.get("/metrics").body).into_owned();
        if m.lines().any(|l| l == "vlmfuse_snapshots_total 1") {
            break;
        }
        assert!(
            std::time::Instant::now() < deadline,
            "no vlmfuse_snapshots_total 1 in /metrics:\n{m}"
        );
        std::thread::sleep(Duration::from_millis(50));
    }
}
