//! `vlmfuse eval` end to end on the shipped rounds file (PAPER-METHOD.md §9), and its errors on bad files.

use crate::support::BIN;
use serde_json::Value;
use std::path::{Path, PathBuf};
use std::process::Command;

fn bin() -> Command {
    Command::new(BIN)
}

fn data() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../tests/data/rounds.jsonl")
}

/// The stdout of a run that must succeed; its stderr otherwise.
fn stdout_of_success(res: std::process::Output) -> String {
    assert!(
        res.status.success(),
        "{}",
        String::from_utf8_lossy(&res.stderr)
    );
    String::from_utf8(res.stdout).unwrap()
}

fn row<'a>(report: &'a Value, name: &str) -> &'a Value {
    report["rows"]
        .as_array()
        .unwrap()
        .iter()
        .find(|r| r["name"] == name)
        .unwrap_or_else(|| panic!("no row {name}"))
}

#[test]
fn eval_emits_spec_rounds_report_and_plots() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("out.jsonl");
    let report = dir.path().join("report.json");
    let plots = dir.path().join("plots");
    let res = bin()
        .arg("eval")
        .arg(data())
        .args(["--ablation", "all", "--quiet"])
        .arg("--emit-rounds")
        .arg(&out)
        .arg("--report")
        .arg(&report)
        .arg("--plots")
        .arg(&plots)
        .output()
        .unwrap();
    let table = stdout_of_success(res);
    for name in [
        "fusion (full method)",
        "ablation: frozen-reputation",
        "ablation: per-model-score",
        "ablation: no-guardrail",
        "ablation: no-context",
        "baseline: majority vote",
        "baseline: vlaad alone",
        "F1 = 1",
    ] {
        assert!(table.contains(name), "table lacks {name}:\n{table}");
    }

    let text = std::fs::read_to_string(&out).unwrap();
    let lines: Vec<Value> = text
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    assert_eq!(lines.len(), 900);
    let input: Vec<Value> = std::fs::read_to_string(data())
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    let mut keys: Vec<String> = lines[0].as_object().unwrap().keys().cloned().collect();
    keys.sort();
    assert_eq!(
        keys,
        ["id", "phi", "pred", "q", "threshold", "w_after", "w_used"]
    );
    for (line, inp) in lines.iter().zip(&input) {
        assert_eq!(line["id"], inp["id"]);
        assert_eq!(line["q"].as_object().unwrap().len(), 14);
        // One threshold, or one per label (the calibration maps it per label).
        let t = |k: &str| match &line["threshold"] {
            Value::Object(m) => m[k].as_f64().unwrap(),
            v => v.as_f64().unwrap(),
        };
        // pred is exactly the labels with q >= their threshold.
        let mut expect: Vec<&str> = line["q"]
            .as_object()
            .unwrap()
            .iter()
            .filter(|(k, q)| q.as_f64().unwrap() >= t(k))
            .map(|(k, _)| k.as_str())
            .collect();
        expect.sort();
        let mut pred: Vec<&str> = line["pred"]
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v.as_str().unwrap())
            .collect();
        pred.sort();
        assert_eq!(pred, expect);
        let labelled = !inp["truth"].is_null();
        assert_eq!(
            !line["phi"].is_null(),
            labelled,
            "phi only on labelled rounds"
        );
        let w: f64 = line["w_after"]
            .as_object()
            .unwrap()
            .values()
            .map(|v| v.as_f64().unwrap())
            .sum();
        assert!((w - 1.0).abs() < 1e-12);
        if !labelled {
            assert_eq!(
                line["w_after"], line["w_used"],
                "unlabelled rounds change nothing"
            );
        }
        // Shapley efficiency is not visible here, but the reporters are the sorted names.
        let names: Vec<&String> = line["w_used"].as_object().unwrap().keys().collect();
        assert_eq!(names, ["videollama2", "videollava", "vlaad"]);
    }

    let rep: Value = serde_json::from_str(&std::fs::read_to_string(&report).unwrap()).unwrap();
    let fusion = &row(&rep, "fusion (full method)")["scores"];
    let best_single = ["vlaad", "videollama2", "videollava"]
        .iter()
        .map(|n| {
            row(&rep, &format!("baseline: {n} alone"))["scores"]["hamming"]
                .as_f64()
                .unwrap()
        })
        .fold(f64::INFINITY, f64::min);
    assert!(
        fusion["hamming"].as_f64().unwrap() < best_single,
        "the fusion must beat the best single model on this file"
    );
    assert!(
        row(&rep, "ablation: no-context")["scores"]["hamming"]
            .as_f64()
            .unwrap()
            > fusion["hamming"].as_f64().unwrap(),
        "context awareness matters on this file"
    );
    for f in ["reputations.svg", "reliability.svg", "ablations.svg"] {
        let svg = std::fs::read_to_string(plots.join(f)).unwrap();
        assert!(
            svg.starts_with("<svg") && svg.contains("</svg>") && svg.len() > 2000,
            "{f}"
        );
    }
}

#[test]
fn frozen_stops_learning_after_the_history() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("out.jsonl");
    let res = bin()
        .arg("eval")
        .arg(data())
        .args(["--frozen", "--split", "0.5", "--quiet", "--emit-rounds"])
        .arg(&out)
        .output()
        .unwrap();
    assert!(res.status.success());
    let lines: Vec<Value> = std::fs::read_to_string(&out)
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    let frozen = &lines[450..];
    assert!(frozen
        .iter()
        .all(|l| l["phi"].is_null() && l["w_after"] == lines[449]["w_after"]));
    assert!(frozen
        .iter()
        .all(|l| l["threshold"] == frozen[0]["threshold"]));
    assert!(lines[..450].iter().any(|l| !l["phi"].is_null()));
}

fn eval_err(content: &str) -> String {
    let dir = tempfile::tempdir().unwrap();
    let f = dir.path().join("bad.jsonl");
    std::fs::write(&f, content).unwrap();
    let res = bin().arg("eval").arg(&f).output().unwrap();
    assert!(!res.status.success(), "must fail on {content:?}");
    String::from_utf8(res.stderr).unwrap()
}

#[test]
fn bad_rounds_files_name_the_line_and_problem() {
    let ok = r#"{"id":"a","context":[1,0,0],"reports":{"m":["brake"]},"truth":["brake"]}"#;
    let e = eval_err(&format!("{ok}\n{ok}\n{{not json\n"));
    assert!(e.contains("line 3"), "{e}");
    let e = eval_err(&format!(
        "{ok}\n{}\n",
        r#"{"context":[1,0,0],"reports":{"m":["fly"]}}"#
    ));
    assert!(e.contains("line 2") && e.contains("\"fly\""), "{e}");
    let e = eval_err(&format!(
        "{ok}\n{}\n",
        r#"{"context":[1,0],"reports":{"m":[]}}"#
    ));
    assert!(
        e.contains("line 2") && e.contains("dimension 2") && e.contains("dimension 3"),
        "{e}"
    );
    let e = eval_err(&format!(
        "{ok}\n{}\n",
        r#"{"context":[1,0,0],"reports":{"":[]}}"#
    ));
    assert!(e.contains("line 2") && e.contains("empty name"), "{e}");
    let e = eval_err(&format!(
        "{ok}\n{}\n",
        r#"{"context":[1,0,0],"reports":{"m":[]},"truth":["warp"]}"#
    ));
    assert!(e.contains("line 2") && e.contains("warp"), "{e}");
    let e = eval_err(&format!(
        "{ok}\n{}\n",
        r#"{"context":[0,0,0],"reports":{"m":[]}}"#
    ));
    assert!(e.contains("line 2") && e.contains("norm 0"), "{e}");
    let e = eval_err(&format!("{ok}\n{}\n", r#"{"context":[1,0,0]}"#));
    assert!(e.contains("line 2") && e.contains("reports"), "{e}");
    let e = eval_err("\n\n");
    assert!(e.contains("no rounds"), "{e}");
    let res = bin()
        .args(["eval", "/nonexistent/rounds.jsonl"])
        .output()
        .unwrap();
    assert!(!res.status.success());
    let res = bin()
        .arg("eval")
        .arg(data())
        .args(["--ablation", "nope"])
        .output()
        .unwrap();
    assert!(String::from_utf8_lossy(&res.stderr).contains("unknown ablation"));
}

/// The table (stdout) and the timing (stderr) meet in one stream as on a terminal: the timing
/// is a line of its own, not the tail of `Final reputations: ...`.
#[test]
fn the_timing_is_a_line_of_its_own() {
    let dir = tempfile::tempdir().unwrap();
    let f = dir.path().join("short.jsonl");
    let text = std::fs::read_to_string(data()).unwrap();
    std::fs::write(&f, text.lines().take(60).collect::<Vec<_>>().join("\n")).unwrap();
    for extra in ["", "--curve 0,all"] {
        let res = Command::new("sh")
            .arg("-c")
            .arg(format!(
                "'{BIN}' eval '{}' --quiet {extra} 2>&1",
                f.display()
            ))
            .output()
            .unwrap();
        assert!(res.status.success());
        let out = String::from_utf8(res.stdout).unwrap();
        let lines: Vec<&str> = out.lines().collect();
        assert!(
            lines.iter().any(|l| l.starts_with("Final reputations:")),
            "{out}"
        );
        assert!(
            lines
                .iter()
                .all(|l| !l.contains("eval took") || l.starts_with("eval took")),
            "{out}"
        );
        assert!(lines.last().unwrap().starts_with("eval took"), "{out}");
    }
}

#[test]
fn a_curve_compares_the_review_queue_with_random_picks() {
    let dir = tempfile::tempdir().unwrap();
    let report = dir.path().join("curve.json");
    let plots = dir.path().join("plots");
    let res = bin()
        .arg("eval")
        .arg(data())
        .args([
            "--frozen", "--curve", "20,all", "--pick", "compare", "--quiet",
        ])
        .arg("--report")
        .arg(&report)
        .arg("--plots")
        .arg(&plots)
        .output()
        .unwrap();
    let table = stdout_of_success(res);
    assert!(
        table.contains("chosen by the review queue and, for comparison, by seed 0")
            && table.contains("20        adaptive (review)")
            && table.contains("20        adaptive (random)"),
        "{table}"
    );
    let v: Value = serde_json::from_str(&std::fs::read_to_string(&report).unwrap()).unwrap();
    let points = v["points"].as_array().unwrap();
    assert_eq!(points.len(), 8, "2 N x 2 picks x 2 methods");
    let at = |n: &str, pick: &str, method: &str| {
        points
            .iter()
            .find(|p| p["requested"] == n && p["pick"] == pick && p["method"] == method)
            .unwrap_or_else(|| panic!("no point {n} {pick} {method}"))["scores"]
            .clone()
    };
    // 20 picked rounds are not 20 random ones; with every truth kept, the picks agree.
    let hf = |s: Value| {
        (
            s["hamming"].as_f64().unwrap(),
            s["micro_f1"].as_f64().unwrap(),
        )
    };
    assert_ne!(
        hf(at("20", "review", "adaptive")),
        hf(at("20", "random", "adaptive"))
    );
    assert_eq!(
        hf(at("all", "review", "paper")),
        hf(at("all", "random", "paper"))
    );
    let svg = std::fs::read_to_string(plots.join("curve.svg")).unwrap();
    assert!(svg.contains("adaptive (review picks)") && svg.contains("paper (random picks)"));

    // Two curves need a curve.
    let res = bin()
        .arg("eval")
        .arg(data())
        .args(["--labelled", "20", "--pick", "compare", "--quiet"])
        .output()
        .unwrap();
    assert!(!res.status.success());
    assert!(String::from_utf8_lossy(&res.stderr).contains("use it with --curve"));
}

#[test]
fn a_review_pool_gives_the_queue_one_sample_per_seed() {
    let run = |seed: &str, pool: &str| {
        let dir = tempfile::tempdir().unwrap();
        let report = dir.path().join("curve.json");
        let res = bin()
            .arg("eval")
            .arg(data())
            .args(["--frozen", "--curve", "20", "--pick", "review", "--quiet"])
            .args([
                "--seed",
                seed,
                "--review-pool",
                pool,
                "--method",
                "adaptive",
            ])
            .arg("--report")
            .arg(&report)
            .output()
            .unwrap();
        let table = stdout_of_success(res);
        let v: Value = serde_json::from_str(&std::fs::read_to_string(&report).unwrap()).unwrap();
        assert_eq!(v["review_pool"].as_f64(), Some(pool.parse().unwrap()));
        let s = v["points"]
            .as_array()
            .unwrap()
            .iter()
            .find(|p| p["method"] == "adaptive")
            .unwrap()["scores"]
            .clone();
        (
            table,
            (
                s["hamming"].as_f64().unwrap(),
                s["micro_f1"].as_f64().unwrap(),
            ),
        )
    };
    let (table, a) = run("1", "0.5");
    assert!(
        table.contains("the review queue over a share 0.5 of the history chosen by seed 1"),
        "{table}"
    );
    // Another seed, another pool, other picks; the same seed, the same picks. The whole pool
    // does not depend on the seed.
    assert_eq!(run("1", "0.5").1, a);
    assert_ne!(run("2", "0.5").1, a);
    assert_eq!(run("1", "1").1, run("2", "1").1);

    for bad in ["0", "1.5", "-0.2", "x"] {
        let res = bin()
            .arg("eval")
            .arg(data())
            .args([
                "--curve",
                "20",
                "--pick",
                "review",
                "--review-pool",
                bad,
                "--quiet",
            ])
            .output()
            .unwrap();
        assert_eq!(res.status.code(), Some(2), "{bad}");
        assert!(
            String::from_utf8_lossy(&res.stderr).contains("--review-pool"),
            "{bad}: {}",
            String::from_utf8_lossy(&res.stderr)
        );
    }
}
