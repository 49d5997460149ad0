//! `/readyz` under `RUST_BACKTRACE=1` in the real binary: the environment is the child's, so
//! it cannot be set for an in-process service.

use crate::support::Server;

/// Issue 10's row: with `RUST_BACKTRACE=1` and an embedder that fails to load, `/readyz` gave a
/// 40-frame backtrace with build paths (14 KB); the reason is one line.
#[test]
fn a_failing_embedder_is_one_line_in_readyz_even_with_backtraces_on() {
    let tmp = tempfile::tempdir().unwrap();
    let fake = vlmfuse_testkit::server::FakeOpenAi::start();
    // The tiny CLIP with its config's MLP width changed: candle's shape-mismatch error, which
    // carries a backtrace when RUST_BACKTRACE is set.
    let toml = vlmfuse_testkit_models::fixtures::clip_embedder_toml(tmp.path());
    let config = tmp.path().join("clip").join("config.json");
    let mut c: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&config).unwrap()).unwrap();
    let w = c["vision_config"]["intermediate_size"].as_u64().unwrap();
    c["vision_config"]["intermediate_size"] = (w + 8).into();
    std::fs::write(&config, c.to_string()).unwrap();
    let mut cfg = String::from("reporters = [\"videollama2\"]\n\n");
    cfg += &toml;
    cfg += &fake.reporter_toml("videollama2", "frames");
    cfg += &fake.labeler_toml();
    let path = tmp.path().join("c.toml");
    std::fs::write(&path, cfg).unwrap();
    let srv = Server::start(
        &tmp.path().join("d"),
        &["--config", path.to_str().unwrap()],
        &[("RUST_BACKTRACE", "1"), ("RUST_LIB_BACKTRACE", "1")],
    );
    let r = srv.get("/readyz");
    assert_eq!(r.status, 503);
    let v = r.json();
    let why = v["components"]["embedder"]["error"].as_str().unwrap();
    eprintln!("embedder: {why}");
    assert!(!why.contains('\n') && !why.contains(".rs:"), "{why}");
    assert!(r.body.len() < 4096, "{} bytes: {v:#}", r.body.len());
}
