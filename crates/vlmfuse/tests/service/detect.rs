//! The object detector in the service (`[detect]`): `/v1/infer` runs it on the clip's frames,
//! answers `detected` with the evidence, and with `feedback = true` sends the decided labels as
//! partial feedback from `detector`, leaving out what the same clip's signals decided. A
//! detector that cannot load makes the service unready for clips, never a 500.
//!
//! The model is the committed tiny YOLO11 (random weights) of the parity test; its detections
//! are meaningless, so the rules here map every class to one label (any persistent object) and
//! a class the model lacks to another (a negative), which makes the outcome certain.

use crate::support::TestApp;
use serde_json::json;
use std::path::PathBuf;
use vlmfuse_testkit::clips::h264_clip;
use vlmfuse_testkit::multipart::multipart;
use vlmfuse_testkit::server::FakeOpenAi;
use vlmfuse_testkit_models::fixtures::clip_embedder_toml;

fn model() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../tests/data/parity/detect/model.onnx")
}

const ALL_CLASSES: &str = "[\"person\", \"bicycle\", \"car\", \"motorcycle\", \"bus\", \"truck\", \
                           \"traffic light\", \"stop sign\"]";

fn config(
    tmp: &std::path::Path,
    fake: &FakeOpenAi,
    model: &std::path::Path,
    extra: &str,
) -> String {
    let mut cfg = format!(
        "reporters = [\"videollama2\"]\n\n[media]\nframes = 4\n\n{extra}\n\
         [detect]\nmodel = {model:?}\nfeedback = true\nconf = 0.1\nframes = 6\n\n\
         [detect.rules]\nmin_frames = 2\nmin_score = 0.0\n\
         path = [[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]]\n\
         [[detect.rules.labels]]\nlabel = \"traffic_light_ahead\"\nclasses = {ALL_CLASSES}\n\
         [[detect.rules.labels]]\nlabel = \"stop\"\nclasses = [\"unicorn\"]\nnegative = true\n\
         [[detect.rules.labels]]\nlabel = \"junction_ahead\"\nclasses = [\"unicorn\"]\nnegative = true\n\n"
    );
    cfg += &clip_embedder_toml(tmp);
    cfg += &fake.reporter_toml("videollama2", "frames");
    cfg += &fake.labeler_toml();
    cfg
}

/// 4 s of a car braking to a standstill at 2 s: the signals decide `stop` (present).
fn braking_track() -> String {
    let mut s = String::from("t_s,speed_mps,accel_mps2,yaw_rate_dps\n");
    for i in 0..=40 {
        let t = i as f64 / 10.0;
        let v = (8.0 - 4.0 * t).max(0.0);
        let a = if t < 2.0 { -4.0 } else { 0.0 };
        s += &format!("{t:.1},{v:.3},{a:.3},0.0\n");
    }
    s
}

fn value(v: &serde_json::Value, label: &str) -> Option<bool> {
    v["labels"]
        .as_array()?
        .iter()
        .find(|d| d["label"] == label)
        .map(|d| d["value"].as_bool().unwrap())
}

#[tokio::test(flavor = "multi_thread")]
#[ignore = "needs assets: scripts/fetch-assets.sh (ONNX Runtime)"]
async fn infer_runs_the_detector_and_feeds_its_labels_back() {
    let tmp = tempfile::tempdir().unwrap();
    let fake = FakeOpenAi::start();
    let cfg = config(tmp.path(), &fake, &model(), "[annotate]\nfeedback = true\n");
    let srv = TestApp::from_toml(tmp.path(), &cfg).await;
    let clip = std::fs::read(h264_clip(tmp.path(), "a.mp4", "testsrc", 4.0)).unwrap();

    // The clip alone: the detector's labels and their evidence, sent as feedback.
    let r = srv
        .post_multipart(multipart(&[("video", "a.mp4", &clip)]))
        .await;
    let v = r.json();
    assert_eq!(r.status, 200, "{v}");
    let d = &v["detected"];
    assert_eq!(d["frames"], 6, "the detector's own 6 frames: {d}");
    assert_eq!(value(d, "traffic_light_ahead"), Some(true), "{d}");
    assert_eq!(value(d, "stop"), Some(false), "{d}");
    let ev = &d["labels"][0]["evidence"][0];
    assert!(ev["frames"].as_u64().unwrap() >= 2, "{ev}");
    assert_eq!(ev["of_frames"], 6);
    assert!(ev["best_box"].as_array().unwrap().len() == 4, "{ev}");
    assert!(ev["class"].is_string() && ev["track_id"].is_u64(), "{ev}");
    assert!(v["timings_ms"]["detect"].as_f64().unwrap() > 0.0, "{v}");
    let fb = &v["detector_feedback"];
    assert_eq!(fb["source"], "detector", "{v}");
    assert_eq!(fb["learned"]["traffic_light_ahead"], true, "{fb}");
    assert_eq!(fb["learned"]["stop"], false, "{fb}");
    assert!(v.get("kinematics_feedback").is_none(), "{v}");
    let st = srv.state().await;
    assert_eq!(st["labelled_rounds"], 1, "{st}");

    // With the signals: they decide `stop` (present), so the detector leaves it out instead
    // of contradicting them (which would refuse its whole feedback).
    let r = srv
        .post_multipart(multipart(&[
            ("video", "a.mp4", &clip),
            ("signals", "a.csv", braking_track().as_bytes()),
        ]))
        .await;
    let v = r.json();
    assert_eq!(r.status, 200, "{v}");
    assert_eq!(v["kinematics_feedback"]["learned"]["stop"], true, "{v}");
    let fb = &v["detector_feedback"];
    assert_eq!(fb["source"], "detector", "{v}");
    assert_eq!(fb["learned"]["traffic_light_ahead"], true, "{fb}");
    assert_eq!(fb["learned"]["junction_ahead"], false, "{fb}");
    assert!(fb["learned"].get("stop").is_none(), "{fb}");
    assert_eq!(v["detected"]["labels"].as_array().unwrap().len(), 3);
}

#[tokio::test(flavor = "multi_thread")]
async fn a_detector_that_cannot_load_makes_clips_unready_not_a_500() {
    let tmp = tempfile::tempdir().unwrap();
    let fake = FakeOpenAi::start();
    let missing = tmp.path().join("nope.onnx");
    let srv = TestApp::from_toml(tmp.path(), &config(tmp.path(), &fake, &missing, "")).await;
    let r = srv.get("/readyz").await;
    assert_eq!(r.status, 503, "{}", r.json());
    assert!(r.json().to_string().contains("detector"), "{}", r.json());
    let clip = std::fs::read(h264_clip(tmp.path(), "a.mp4", "testsrc", 1.0)).unwrap();
    let r = srv
        .post_multipart(multipart(&[("video", "a.mp4", &clip)]))
        .await;
    assert_eq!(r.status, 503, "{}", r.json());
    assert!(
        r.json()["error"].as_str().unwrap().contains("nope.onnx"),
        "{}",
        r.json()
    );
    // /v1/fuse does not need the detector.
    let ctx: Vec<f64> = vec![0.1; 8];
    let r = srv
        .post(
            "/v1/fuse",
            &json!({"context": ctx, "reports": {"videollama2": ["brake"]}}),
        )
        .await;
    assert!(r.status < 500, "{}", r.json());
}

#[test]
fn detect_config_reads_flags_and_refuses_labels_outside_the_ontology() {
    let args = vlmfuse::config::ServeArgs::try_parse_from([
        "serve",
        "--detect-model",
        "/m.onnx",
        "--detect-conf",
        "0.4",
        "--detect-tracker",
        "bytetrack",
        "--detect-feedback",
        "true",
    ])
    .unwrap();
    let cfg = vlmfuse::Config::load(&args).unwrap();
    assert_eq!(
        cfg.detect.model.as_deref(),
        Some(std::path::Path::new("/m.onnx"))
    );
    assert_eq!(cfg.detect.conf, 0.4);
    assert!(cfg.detect.feedback);
    assert_eq!(
        cfg.detect.tracker_config().kind,
        vlmfuse_detect::TrackerKind::Bytetrack
    );
    let bad = "[detect]\nmodel = \"/m.onnx\"\n[[detect.rules.labels]]\nlabel = \"flying\"\nclasses = [\"bird\"]\n";
    let e = vlmfuse::Config::from_toml(bad).unwrap_err();
    assert!(format!("{e:#}").contains("flying"), "{e:#}");
    assert!(vlmfuse::Config::from_toml("[detect]\nconf = 2.0\n").is_err());
    assert!(vlmfuse::Config::from_toml("[detect]\nframes = 500\n").is_err());
    assert!(vlmfuse::Config::from_toml("[detect]\nframes = 24\n").is_ok());
    assert!(vlmfuse::Config::from_toml("[detect]\nmodle = \"x\"\n").is_err());
    assert!(vlmfuse::Config::from_toml("[detect.tracker]\nkind = \"sort\"\n").is_err());
}
