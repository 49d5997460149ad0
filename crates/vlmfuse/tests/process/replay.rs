//! The service (the real binary) against `vlmfuse eval`: replaying a rounds file through `/v1/fuse` then
//! `/v1/feedback` must give eval's posteriors and reputations (PAPER-METHOD.md §9's sequential protocol),
//! and a `kill -9` in the middle followed by a restart must lose nothing acknowledged and continue
//! with bit-identical numbers.

use crate::support::*;
use serde_json::{json, Value};
use std::path::{Path, PathBuf};
use std::process::Command;
use vlmfuse_testkit::rounds::{generate_rounds, read_jsonl, sorted_reporters, write_jsonl};

/// The lead's realistic file when present, else a generated one.
pub(crate) fn rounds(tmp: &Path) -> (Vec<Value>, PathBuf) {
    let shipped = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../tests/data/rounds.jsonl");
    let rounds = if shipped.exists() {
        read_jsonl(&shipped)
    } else {
        generate_rounds(300, 32, 7)
    };
    let path = tmp.join("rounds.jsonl");
    write_jsonl(&path, &rounds);
    (rounds, path)
}

fn eval(file: &Path, out: &Path) -> Vec<Value> {
    let o = Command::new(BIN)
        .args([
            "eval",
            file.to_str().unwrap(),
            "--split",
            "0",
            "--quiet",
            "--emit-rounds",
        ])
        .arg(out)
        .env_remove("VLMFUSE_CONFIG")
        .output()
        .unwrap();
    assert!(
        o.status.success(),
        "eval failed: {}",
        String::from_utf8_lossy(&o.stderr)
    );
    read_jsonl(out)
}

/// What the service said about one round.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct Seen {
    pub(crate) fuse: Value,
    pub(crate) feedback: Option<Value>,
}

pub(crate) fn without_truth(r: &Value) -> Value {
    let mut r = r.clone();
    r.as_object_mut().unwrap().remove("truth");
    r
}

pub(crate) fn truth(r: &Value) -> Option<Value> {
    r.get("truth").filter(|t| !t.is_null()).cloned()
}

/// Where an interrupted replay got to.
#[derive(Default)]
pub(crate) struct Progress {
    pub(crate) seen: Vec<Seen>,
    /// A round whose fuse was acknowledged (`round_id`, answer) but whose feedback was not.
    pub(crate) pending: Option<(String, Value)>,
}

/// Replays the rounds not yet seen; stops at the first transport error (the server died) and
/// returns false.
pub(crate) fn replay(addr: &str, rounds: &[Value], prog: &mut Progress) -> bool {
    while prog.seen.len() < rounds.len() {
        let i = prog.seen.len();
        let r = &rounds[i];
        let (round_id, fuse) = match prog.pending.take() {
            Some(p) => p,
            None => {
                // A request id per round, as a careful client sends: the fuse in flight at the
                // kill is retried after the restart under the same id, so a round that was
                // committed but never acknowledged is answered from the store instead of being
                // stored twice (an orphan copy would join the adaptive pool and change every
                // later posterior).
                let mut body = without_truth(r);
                body["request_id"] = json!(format!("replay-{i}"));
                let Ok(resp) = try_post(addr, "/v1/fuse", &body) else {
                    return false;
                };
                // Unavailable (a replica whose writer is gone, until another takes over): as
                // if it had not answered; the retry repeats the request id.
                if resp.status == 503 {
                    return false;
                }
                assert_eq!(
                    resp.status,
                    200,
                    "round {i}: {}",
                    String::from_utf8_lossy(&resp.body)
                );
                let v = resp.json();
                (v["round_id"].as_str().unwrap().to_string(), v)
            }
        };
        let mut feedback = None;
        if let Some(t) = truth(r) {
            let Ok(resp) = try_post(
                addr,
                "/v1/feedback",
                &json!({"round_id": round_id, "labels": t}),
            ) else {
                prog.pending = Some((round_id, fuse));
                return false;
            };
            if resp.status == 503 {
                prog.pending = Some((round_id, fuse));
                return false;
            }
            assert_eq!(
                resp.status,
                200,
                "round {i}: {}",
                String::from_utf8_lossy(&resp.body)
            );
            feedback = Some(resp.json());
        }
        prog.seen.push(Seen { fuse, feedback });
    }
    true
}

fn close(a: f64, b: f64, what: &str) {
    assert!((a - b).abs() <= 1e-12, "{what}: service {a} vs eval {b}");
}

fn num(v: &Value) -> f64 {
    v.as_f64().unwrap_or_else(|| panic!("not a number: {v}"))
}

/// The service's answers against eval's emitted rounds.
fn compare_with_eval(seen: &[Seen], emitted: &[Value]) {
    assert_eq!(seen.len(), emitted.len());
    for (i, (s, e)) in seen.iter().zip(emitted).enumerate() {
        let f = &s.fuse;
        for (label, q) in e["q"].as_object().unwrap() {
            close(
                num(&f["posteriors"][label]),
                num(q),
                &format!("round {i} q[{label}]"),
            );
        }
        // One threshold, or one per label where they differ (the adaptive calibration maps it
        // per label): the service's `thresholds` then carries the same map.
        let te = |label: &str| match &e["threshold"] {
            Value::Object(m) => num(&m[label]),
            v => num(v),
        };
        let tf = |label: &str| match f.get("thresholds") {
            Some(Value::Object(m)) => num(&m[label]),
            _ => num(&f["threshold"]),
        };
        for label in e["q"].as_object().unwrap().keys() {
            close(
                tf(label),
                te(label),
                &format!("round {i} threshold[{label}]"),
            );
        }
        for (name, w) in e["w_used"].as_object().unwrap() {
            close(
                num(&f["reputations"][name]),
                num(w),
                &format!("round {i} w_used[{name}]"),
            );
        }
        let near_threshold = e["q"]
            .as_object()
            .unwrap()
            .iter()
            .any(|(label, q)| (num(q) - te(label)).abs() < 1e-9);
        if !near_threshold {
            assert_eq!(f["labels"], e["pred"], "round {i} labels");
        }
        match (&s.feedback, e["phi"].as_object()) {
            (None, None) => {
                for (name, w) in e["w_after"].as_object().unwrap() {
                    close(
                        num(&f["reputations"][name]),
                        num(w),
                        &format!("round {i} w_after[{name}]"),
                    );
                }
            }
            (Some(fb), Some(phi)) => {
                for (name, p) in phi {
                    let got = fb["shapley"].get(name).map(num).unwrap_or(0.0);
                    close(got, num(p), &format!("round {i} phi[{name}]"));
                }
                for (name, w) in e["w_after"].as_object().unwrap() {
                    close(
                        num(&fb["reputations"][name]),
                        num(w),
                        &format!("round {i} w_after[{name}]"),
                    );
                }
            }
            (a, b) => panic!("round {i}: service feedback {a:?} but eval phi {b:?}"),
        }
    }
}

/// The same answers, bit for bit (round ids included: the retried fuse reuses its request id,
/// so the kill leaves no orphan round behind).
pub(crate) fn assert_identical(a: &[Seen], b: &[Seen]) {
    assert_eq!(a.len(), b.len());
    for (i, (x, y)) in a.iter().zip(b).enumerate() {
        assert_eq!(x.fuse, y.fuse, "round {i}: fuse differs");
        assert_eq!(x.feedback, y.feedback, "round {i}: feedback differs");
    }
}

#[test]
fn replay_equals_eval_and_a_kill_9_loses_nothing() {
    let tmp = tempfile::tempdir().unwrap();
    let (rounds, file) = rounds(tmp.path());
    let reporters = sorted_reporters(&rounds).join(",");

    // Uninterrupted run (A) beside eval, while the interrupted run (B) goes in this thread.
    let (dir_a, file_a, rounds_a, reporters_a) = (
        tmp.path().join("a"),
        file.clone(),
        rounds.clone(),
        reporters.clone(),
    );
    let uninterrupted = std::thread::spawn(move || {
        let emitted = eval(&file_a, &dir_a.with_extension("emit.jsonl"));
        let srv = Server::start(&dir_a, &["--reporters", &reporters_a], &[]);
        let mut prog = Progress::default();
        assert!(replay(&srv.addr, &rounds_a, &mut prog));
        (emitted, prog.seen, srv.state())
    });

    // The interrupted run snapshots its engine every few events, so its restart loads a
    // snapshot and replays only the tail: which must change nothing.
    let dir_b = tmp.path().join("b");
    let args_b = ["--reporters", reporters.as_str(), "--snapshot-every", "37"];
    let mut srv = Server::start(&dir_b, &args_b, &[]);
    let mut prog = Progress::default();
    let half = rounds.len() / 2;
    assert!(replay(&srv.addr, &rounds[..half], &mut prog));
    // Kill -9 once the second half has begun to commit (a fixed delay raced the debug build's
    // speed), with requests in flight.
    let pid = srv.child.id().to_string();
    let addr = srv.addr.clone();
    let killer = std::thread::spawn(move || {
        let deadline = std::time::Instant::now() + std::time::Duration::from_secs(60);
        while std::time::Instant::now() < deadline {
            let stored = crate::support::client()
                .get(format!("http://{addr}/v1/state"))
                .send()
                .ok()
                .and_then(|r| r.json::<Value>().ok())
                .and_then(|v| v["rounds"].as_u64())
                .unwrap_or(0);
            if stored as usize > half + 2 {
                break;
            }
            std::thread::sleep(std::time::Duration::from_millis(2));
        }
        Command::new("kill").args(["-9", &pid]).status().unwrap();
    });
    let finished = replay(&srv.addr, &rounds, &mut prog);
    killer.join().unwrap();
    assert!(
        !finished,
        "the replay finished before the kill; kill earlier"
    );
    srv.kill9();
    let acked = prog.seen.len();
    let acked_feedback: Vec<(usize, Value)> = prog
        .seen
        .iter()
        .enumerate()
        .filter_map(|(i, s)| s.feedback.clone().map(|f| (i, f)))
        .collect();
    assert!(acked > half, "nothing got through after the half");

    let srv = Server::start(&dir_b, &args_b, &[("RUST_LOG", "info")]);
    let log = std::fs::read_to_string(dir_b.join("server.log")).unwrap();
    assert!(
        log.contains("engine loaded from a snapshot"),
        "the restart did not use a snapshot: {log}"
    );
    let st = srv.state();
    let labelled = st["labelled_rounds"].as_u64().unwrap() as usize;
    // Every acknowledged feedback is there; at most the one in flight was committed unseen.
    assert!(
        labelled >= acked_feedback.len() && labelled <= acked_feedback.len() + 1,
        "{labelled} vs {}",
        acked_feedback.len()
    );
    for (i, fb) in &acked_feedback {
        let body = json!({"round_id": fb["round_id"], "labels": truth(&rounds[*i]).unwrap()});
        let r = try_post(&srv.addr, "/v1/feedback", &body).unwrap();
        assert_eq!(r.status, 200);
        assert_eq!(
            r.header("x-vlmfuse-repeated"),
            Some("true"),
            "round {i} was not stored"
        );
        assert_eq!(
            &r.json(),
            fb,
            "round {i}: the repeat differs from the acknowledged answer"
        );
    }
    assert_eq!(
        srv.state(),
        st,
        "repeating acknowledged feedback changed the state"
    );
    assert!(
        replay(&srv.addr, &rounds, &mut prog),
        "the restarted server failed"
    );
    let state_b = srv.state();

    let (emitted, seen_a, state_a) = uninterrupted.join().unwrap();
    compare_with_eval(&seen_a, &emitted);
    assert_identical(&seen_a, &prog.seen);
    for key in [
        "reputations",
        "labelled_rounds",
        "threshold",
        "reporters",
        "dim",
    ] {
        assert_eq!(state_a[key], state_b[key], "final state {key} differs");
    }
}

fn import(file: &Path, dir: &Path, reporters: &str) -> std::process::Output {
    import_command(file, dir, reporters, &[]).output().unwrap()
}

/// `vlmfuse import FILE --quiet --reporters R --data-dir DIR`, with `extra` arguments.
fn import_command(file: &Path, dir: &Path, reporters: &str, extra: &[&str]) -> Command {
    let mut c = Command::new(BIN);
    c.args(["import", file.to_str().unwrap(), "--quiet", "--reporters"])
        .arg(reporters)
        .arg("--data-dir")
        .arg(dir)
        .args(extra)
        .env_remove("VLMFUSE_CONFIG");
    c
}

/// Rounds stored in a data directory (0 when there is none yet).
fn stored_rounds(dir: &Path) -> u64 {
    vlmfuse_store::Store::open_read_only(dir)
        .and_then(|s| s.counts())
        .map_or(0, |c| c.0)
}

/// `vlmfuse import` of the first part of a rounds file, then the rest through the service:
/// the service continues exactly as `eval` over the whole file (the import stored the events a
/// live writer would have), and starts from the snapshot the import left. A file with bad
/// lines is refused with their numbers and stores nothing.
#[test]
fn an_imported_history_continues_as_eval_does() {
    let tmp = tempfile::tempdir().unwrap();
    let (rounds, file) = rounds(tmp.path());
    let reporters = sorted_reporters(&rounds).join(",");
    let emitted = eval(&file, &tmp.path().join("emit.jsonl"));
    let dir = tmp.path().join("data");

    // Bad lines: an unknown reporter, another dimension, and not JSON.
    let mut bad: Vec<Value> = rounds[..5].to_vec();
    let mut stranger = rounds[5].clone();
    stranger["reports"]["stranger"] = json!([]);
    bad.push(stranger);
    let mut short = rounds[6].clone();
    short["context"].as_array_mut().unwrap().pop();
    bad.push(short);
    let bad_file = tmp.path().join("bad.jsonl");
    write_jsonl(&bad_file, &bad);
    let mut text = std::fs::read_to_string(&bad_file).unwrap();
    text.push_str("{not json\n");
    std::fs::write(&bad_file, text).unwrap();
    let o = import(&bad_file, &dir, &reporters);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success(), "a bad file was imported");
    for line in [
        "line 6:",
        "line 7:",
        "line 8:",
        "3 bad line(s)",
        "nothing was imported",
    ] {
        assert!(err.contains(line), "{line:?} missing from: {err}");
    }
    let (stored, _) = vlmfuse_store::Store::open_read_only(&dir)
        .unwrap()
        .counts()
        .unwrap();
    assert_eq!(stored, 0, "a refused file stored rounds");

    let cut = rounds.len() * 2 / 3;
    let head = tmp.path().join("head.jsonl");
    write_jsonl(&head, &rounds[..cut]);
    let o = import(&head, &dir, &reporters);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));

    let srv = Server::start(&dir, &["--reporters", &reporters], &[("RUST_LOG", "info")]);
    let st = srv.state();
    assert_eq!(st["rounds"].as_u64(), Some(cut as u64));
    let log = std::fs::read_to_string(dir.join("server.log")).unwrap();
    assert!(
        log.contains("engine loaded from a snapshot"),
        "the start replayed everything: {log}"
    );
    let mut prog = Progress::default();
    assert!(replay(&srv.addr, &rounds[cut..], &mut prog));
    compare_with_eval(&prog.seen, &emitted[cut..]);
}

/// Ctrl-C in the middle of an import (chunks already committed) rolls the directory back: a
/// file imports whole or not at all.
#[test]
fn an_interrupted_import_stores_nothing() {
    let tmp = tempfile::tempdir().unwrap();
    let rounds = generate_rounds(6000, 32, 9);
    let reporters = sorted_reporters(&rounds).join(",");
    let file = tmp.path().join("rounds.jsonl");
    write_jsonl(&file, &rounds);
    let dir = tmp.path().join("data");
    let mut child = import_command(&file, &dir, &reporters, &["--chunk", "50"])
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let stored = stored_rounds;
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(120);
    while stored(&dir) == 0 {
        assert!(
            child.try_wait().unwrap().is_none(),
            "the import ended before a chunk was seen"
        );
        assert!(std::time::Instant::now() < deadline, "no chunk committed");
        std::thread::sleep(std::time::Duration::from_millis(5));
    }
    let mid = stored(&dir);
    Command::new("kill")
        .args(["-INT", &child.id().to_string()])
        .status()
        .unwrap();
    let out = child.wait_with_output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success(),
        "the import finished before the interrupt"
    );
    assert!(err.contains("interrupted at line"), "{err}");
    assert!(err.contains("as it was before"), "{err}");
    assert!(mid > 0 && (mid as usize) < rounds.len());
    assert_eq!(stored(&dir), 0, "{mid} rounds were committed and stayed");
}

/// A bad line at the end of a long file: the check runs beside the import, so chunks may be
/// committed before it is found; the import stops, rolls back, and reports the line.
#[test]
fn a_bad_last_line_rolls_back_the_chunks_before_it() {
    let tmp = tempfile::tempdir().unwrap();
    let rounds = generate_rounds(3000, 32, 5);
    let reporters = sorted_reporters(&rounds).join(",");
    let file = tmp.path().join("rounds.jsonl");
    write_jsonl(&file, &rounds);
    let mut text = std::fs::read_to_string(&file).unwrap();
    text.push_str("{\"context\": [1.0], \"reports\": {}}\n");
    std::fs::write(&file, text).unwrap();
    let dir = tmp.path().join("data");
    let o = import_command(&file, &dir, &reporters, &["--chunk", "50"])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success(), "a bad file was imported");
    for want in ["line 3001:", "1 bad line(s)", "nothing was imported"] {
        assert!(err.contains(want), "{want:?} missing from: {err}");
    }
    assert_eq!(stored_rounds(&dir), 0, "a refused file left rounds stored");
}
