//! `vlmfuse detect IMAGE|CLIP`: the committed tiny YOLO11 on a parity frame gives exactly
//! ultralytics' boxes (as JSON), a clip is sampled and tracked, and a missing model or input is
//! an error that names it.

use crate::support::BIN;
use serde_json::Value;
use std::path::{Path, PathBuf};
use std::process::Command;

fn data(file: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../tests/data/parity/detect")
        .join(file)
}

fn run(args: &[&str]) -> (bool, String, String) {
    let out = Command::new(BIN)
        .arg("detect")
        .args(args)
        .env_remove("VLMFUSE_CONFIG")
        .env_remove("VLMFUSE_DETECT_MODEL")
        .output()
        .unwrap();
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

#[test]
#[ignore = "needs assets: scripts/fetch-assets.sh (ONNX Runtime)"]
fn an_image_gives_ultralytics_boxes_and_a_clip_is_tracked() {
    let model = data("model.onnx");
    let frame = data("frame_4_1280x720.png");
    let (ok, out, err) = run(&[
        frame.to_str().unwrap(),
        "--model",
        model.to_str().unwrap(),
        "--json",
    ]);
    assert!(ok, "{err}");
    let v: Value = serde_json::from_str(&out).unwrap();
    let got = v["frames"][0]["detections"].as_array().unwrap();
    // ultralytics' predict() at its defaults (conf 0.25, iou 0.7) on the same frame.
    let reference: Value =
        serde_json::from_str(&std::fs::read_to_string(data("detect.json")).unwrap()).unwrap();
    let want = reference["frames"][4]["runs"][0]["boxes"]
        .as_array()
        .unwrap();
    assert_eq!(got.len(), want.len());
    for (g, w) in got.iter().zip(want) {
        assert_eq!(g["class"].as_u64(), w[5].as_u64(), "{g} {w}");
        for k in 0..4 {
            let d = g["box"][k].as_f64().unwrap() - w[k].as_f64().unwrap();
            assert!(d.abs() < 1e-3, "{g} {w}");
        }
    }
    assert!(got[0]["name"].is_string());
    // One frame: every label undecided, with why.
    let u = v["detected"]["undecided"].as_array().unwrap();
    assert_eq!(u.len(), 3);
    assert!(
        u[0]["reason"].as_str().unwrap().contains("1 sampled frame"),
        "{u:?}"
    );

    // A clip: its frames sampled, tracked, and the readable report.
    let tmp = tempfile::tempdir().unwrap();
    let clip = vlmfuse_testkit::clips::h264_clip(tmp.path(), "c.mp4", "testsrc", 2.0);
    let (ok, out, err) = run(&[
        clip.to_str().unwrap(),
        "--model",
        model.to_str().unwrap(),
        "--frames",
        "5",
    ]);
    assert!(ok, "{err}");
    assert!(out.contains("5 frame(s)"), "{out}");
    assert!(out.contains("traffic_light_ahead"), "{out}");
}

#[test]
fn a_missing_model_or_input_is_an_error_naming_it() {
    let frame = data("frame_1_97x61.png");
    let (ok, _, err) = run(&[frame.to_str().unwrap()]);
    assert!(!ok);
    assert!(err.contains("--model"), "{err}");
    let (ok, _, err) = run(&[frame.to_str().unwrap(), "--model", "/nonexistent/yolo.onnx"]);
    assert!(!ok);
    assert!(err.contains("/nonexistent/yolo.onnx"), "{err}");
    let model = data("model.onnx");
    let (ok, _, err) = run(&["/nonexistent/x.png", "--model", model.to_str().unwrap()]);
    assert!(!ok);
    assert!(
        err.contains("x.png") || err.contains("ONNX Runtime"),
        "{err}"
    );
}
