//! `vlmfuse annotate FILE|-`: the kinematic rules on a signal track, readable and as JSON, the
//! errors on bad tracks, and `--simulate`'s report.

use crate::support::BIN;
use serde_json::Value;
use std::io::Write;
use std::path::Path;
use std::process::{Command, Stdio};

fn track() -> String {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../tests/data/signals_brake_stop.csv")
        .display()
        .to_string()
}

fn run(args: &[&str], stdin: Option<&[u8]>) -> (bool, String, String) {
    let mut child = Command::new(BIN)
        .arg("annotate")
        .args(args)
        .env_remove("VLMFUSE_CONFIG")
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let mut input = child.stdin.take().unwrap();
    if let Some(b) = stdin {
        input.write_all(b).unwrap();
    }
    drop(input);
    let out = child.wait_with_output().unwrap();
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

#[test]
fn annotate_derives_labels_with_their_evidence() {
    let (ok, out, err) = run(&[&track(), "--json", "--duration", "6"], None);
    assert!(ok, "{err}");
    let v: Value = serde_json::from_str(&out).unwrap();
    let value = |l: &str| {
        v["labels"]
            .as_array()
            .unwrap()
            .iter()
            .find(|d| d["label"] == l)
            .map(|d| d["value"].as_bool().unwrap())
    };
    assert_eq!(value("brake"), Some(true), "{v}");
    assert_eq!(value("stop"), Some(true), "{v}");
    assert_eq!(value("accelerate"), Some(false), "{v}");
    assert_eq!(value("merge"), Some(false), "{v}");
    // Readable, from standard input.
    let csv = std::fs::read(track()).unwrap();
    let (ok, out, err) = run(&["-"], Some(&csv));
    assert!(ok, "{err}");
    assert!(out.contains("brake       yes"), "{out}");
    assert!(out.contains("accel_mps2 = -4.000"), "{out}");
    // A track that does not cover the clip, and one going back in time: named, exit 1.
    let (ok, _, err) = run(&[&track(), "--duration", "30"], None);
    assert!(!ok);
    assert!(err.contains("does not cover"), "{err}");
    let (ok, _, err) = run(&["-"], Some(b"t_s,speed_mps\n0,1\n1,1\n0.5,1\n"));
    assert!(!ok);
    assert!(
        err.contains("line 4") && err.contains("non_monotonic_time"),
        "{err}"
    );
}

#[test]
fn annotate_simulate_reports_precision_and_recall() {
    let (ok, out, err) = run(&["--simulate", "4", "--json"], None);
    assert!(ok, "{err}");
    let v: Value = serde_json::from_str(&out).unwrap();
    let labels = v["labels"].as_array().unwrap();
    assert_eq!(labels.len(), 6, "{v}");
    for l in labels {
        assert!(l["precision"].as_f64().unwrap_or(1.0) >= 0.9, "{l}");
    }
    let (ok, _, err) = run(&["--simulate", "0"], None);
    assert!(!ok && err.contains("at least 1"), "{err}");
}
