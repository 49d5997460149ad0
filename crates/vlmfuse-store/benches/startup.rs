//! Start-up time of the service's state: rebuilding the engine from a database holding 100k
//! labelled rounds (issue 3 asks for at most 5 s). `cargo bench -p vlmfuse-store --bench startup`
//! [-- ROUNDS DIM].

use std::collections::BTreeMap;
use std::time::Instant;
use vlmfuse_fusion::{Engine, FusionConfig, Ontology, RoundRecord};
use vlmfuse_store::{Identity, NewRound, Store, StoredFeedback};

fn main() {
    let args: Vec<String> = std::env::args()
        .skip(1)
        .filter(|a| a != "--bench")
        .collect();
    let n: u64 = args.first().and_then(|a| a.parse().ok()).unwrap_or(100_000);
    let d: usize = args.get(1).and_then(|a| a.parse().ok()).unwrap_or(128);
    let reporters: Vec<String> = ["videollama2", "videollava", "vlaad"]
        .map(String::from)
        .to_vec();
    let ontology = Ontology::paper();
    let l = ontology.len();
    let fresh = || Engine::new(FusionConfig::paper(), ontology.clone(), reporters.clone()).unwrap();
    let empty = fresh();
    let id = Identity {
        reporters: reporters.clone(),
        labels: ontology.labels().iter().map(|x| x.id.clone()).collect(),
    };

    let dir = tempfile::tempdir().unwrap();
    let mut store = Store::open(dir.path()).unwrap();
    store.check_identity(&id).unwrap();
    let fill = Instant::now();
    let mut s: u64 = 0x1234_5678;
    let mut next = move || {
        s = s
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (s >> 11) as f64 / (1u64 << 53) as f64
    };
    // Inference against an empty engine is microseconds and gives well-formed signals; what the
    // rebuild reads (context, reports, q, truth, outcome) has the real sizes.
    let chunk = 5_000u64;
    let mut outcome = None;
    let mut seq = 0u64;
    while seq < n {
        let m = chunk.min(n - seq);
        let mut rounds = Vec::with_capacity(m as usize);
        let mut fbs = Vec::with_capacity(m as usize);
        for i in 0..m {
            let mut reports = BTreeMap::new();
            for r in &reporters {
                let labs: Vec<String> = (0..l)
                    .filter(|_| next() < 0.15)
                    .map(|k| ontology.id(k).to_string())
                    .collect();
                reports.insert(r.clone(), labs);
            }
            let rec = RoundRecord {
                id: None,
                context: (0..d).map(|_| next() - 0.5).collect(),
                reports,
                truth: Some(
                    (0..l)
                        .filter(|_| next() < 0.15)
                        .map(|k| ontology.id(k).to_string())
                        .collect(),
                ),
            };
            let (round, truth) = empty.parse(&rec).unwrap();
            let mut inf = empty.infer(&round);
            inf.q = (0..l).map(|_| next()).collect();
            let truth = truth.unwrap();
            let o = outcome
                .get_or_insert_with(|| empty.credit(&inf.signals, &inf.w_used, &truth, 0))
                .clone();
            fbs.push(StoredFeedback {
                seq: seq + i,
                labelled_order: seq + i,
                rounds_before: seq + m,
                truth,
                outcome: o,
                source: "human".into(),
            });
            rounds.push(NewRound {
                round,
                inference: inf,
                request: serde_json::json!({ "reports": rec.reports }),
                created_ms: 0,
                thumbnails: Vec::new(),
            });
        }
        store.insert_rounds(seq, &rounds).unwrap();
        store.insert_feedback(&fbs).unwrap();
        seq += m;
    }
    drop(store);
    let size = std::fs::metadata(dir.path().join(vlmfuse_store::DB_FILE))
        .map(|m| m.len())
        .unwrap_or(0);
    eprintln!(
        "filled {n} labelled rounds (d = {d}) in {:.1} s, database {:.0} MB",
        fill.elapsed().as_secs_f64(),
        size as f64 / 1e6
    );

    for run in 0..3 {
        let t = Instant::now();
        let mut store = Store::open(dir.path()).unwrap();
        store.check_identity(&id).unwrap();
        let mut engine = fresh();
        let rep = store.load_engine(&mut engine).unwrap();
        let secs = t.elapsed().as_secs_f64();
        assert_eq!(rep.labelled, n);
        println!(
            "startup run {run}: open + rebuild of {} labelled rounds in {secs:.3} s ({:.1} us/round)",
            rep.labelled,
            secs * 1e6 / n as f64
        );
    }
}
