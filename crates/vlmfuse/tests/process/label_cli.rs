//! `vlmfuse label FILE|-`: the served labeler on the command line, readable and as JSON, and its
//! errors on bad input.

use crate::support::BIN;
use serde_json::Value;
use std::io::Write;
use std::process::{Command, Stdio};

/// The served labeler's model files; panics, naming the fetch script, when they are missing.
fn have_assets() {
    vlmfuse_testkit_models::assets::require_assets();
}

#[test]
#[ignore = "needs assets: scripts/fetch-assets.sh"]
fn label_reads_stdin_and_jsonl_and_shows_the_evidence() {
    have_assets();
    // One answer from standard input, readable.
    let mut child = Command::new(BIN)
        .args(["label", "-", "--quiet"])
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    child
        .stdin
        .take()
        .unwrap()
        .write_all(b"No need to stop, just slow down.\n")
        .unwrap();
    let out = child.wait_with_output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{err}");
    let text = String::from_utf8(out.stdout).unwrap();
    let mut lines = text.lines();
    assert_eq!(lines.next(), Some("brake"), "{text}");
    assert!(
        text.contains("+ brake") && text.contains("\"No need to stop, just slow down.\""),
        "{text}"
    );
    assert!(
        text.contains("- stop") && text.contains("negated"),
        "{text}"
    );

    // JSON Lines in, JSON out, ids kept.
    let dir = tempfile::tempdir().unwrap();
    let f = dir.path().join("answers.jsonl");
    std::fs::write(
        &f,
        "{\"id\": \"a-1\", \"text\": \"Stop at the red light.\"}\n\n\"Merge left after checking your mirrors.\"\n",
    )
    .unwrap();
    let out = Command::new(BIN)
        .args(["label", "--jsonl", "--json", "--quiet"])
        .arg(&f)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let rows: Vec<Value> = String::from_utf8(out.stdout)
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    assert_eq!(rows.len(), 2);
    assert_eq!(rows[0]["id"], "a-1");
    assert_eq!(rows[0]["line"], 1);
    assert_eq!(
        rows[0]["labels"],
        serde_json::json!(["stop", "traffic_light_ahead"])
    );
    assert_eq!(rows[1]["line"], 3);
    assert_eq!(
        rows[1]["labels"],
        serde_json::json!(["merge", "check_blind_spot"])
    );
    assert!(rows[1]["evidence"]
        .as_array()
        .is_some_and(|e| !e.is_empty()));
}

#[test]
fn label_refuses_bad_input_with_the_line() {
    let dir = tempfile::tempdir().unwrap();
    let f = dir.path().join("bad.jsonl");
    std::fs::write(&f, "\"fine\"\n{\"txt\": \"typo\"}\n").unwrap();
    let out = Command::new(BIN)
        .args(["label", "--jsonl", "--quiet"])
        .arg(&f)
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("bad.jsonl:2") && err.contains("\"text\""),
        "{err}"
    );
    let out = Command::new(BIN)
        .args(["label", "--quiet"])
        .arg(dir.path().join("missing.txt"))
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("cannot read") && err.contains("missing.txt"),
        "{err}"
    );
}
