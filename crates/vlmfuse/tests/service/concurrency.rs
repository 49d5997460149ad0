//! Concurrent clients get what a sequential replay in the service's arrival order gives: rounds
//! fused in parallel, then labelled from several tasks at once, must produce the same credits,
//! reputations and final state as one client replaying the feedback in the labelling order the
//! service reported (`labelled_rounds` in each answer).

use crate::support::TestApp;
use serde_json::{json, Value};
use std::collections::BTreeMap;
use std::sync::{Arc, Mutex};
use vlmfuse::Config;
use vlmfuse_testkit::rounds::generate_rounds;

const CLIENTS: usize = 8;

fn strip_ids(v: &Value) -> Value {
    let mut v = v.clone();
    v.as_object_mut().unwrap().remove("round_id");
    v.as_object_mut().unwrap().remove("id");
    v
}

/// Runs `f(i)` for every round index, `CLIENTS` tasks at a time, each taking every
/// `CLIENTS`-th index.
async fn in_parallel<F, Fut>(n: usize, f: F)
where
    F: Fn(usize) -> Fut + Send + Sync + 'static,
    Fut: std::future::Future<Output = ()> + Send,
{
    let f = Arc::new(f);
    let tasks: Vec<_> = (0..CLIENTS)
        .map(|t| {
            let f = f.clone();
            tokio::spawn(async move {
                for i in (t..n).step_by(CLIENTS) {
                    f(i).await;
                }
            })
        })
        .collect();
    for t in tasks {
        t.await.unwrap();
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn concurrent_feedback_equals_a_sequential_replay() {
    let tmp = tempfile::tempdir().unwrap();
    let rounds: Arc<Vec<Value>> = Arc::new(
        generate_rounds(160, 16, 11)
            .into_iter()
            .filter(|r| r.get("truth").is_some())
            .collect(),
    );
    let n = rounds.len();
    // Fuses from several clients are inferred against the state as it stands, which the
    // rounds observed just before change as soon as unlabelled rounds teach. Under the default
    // `serve = "switch"` the whole-pool Dawid-Skene learns from the first unlabelled round, so
    // which concurrent fuse saw which observed rounds is a matter of timing (docs/METHOD.md §6,
    // requests in flight). With the vote fallback nothing unlabelled changes an inference
    // before the first label, so phase 1 is order-free and this test isolates what it is about:
    // the writer serialising concurrent feedback exactly as a sequential replay would.
    let cfg = || {
        let mut c = Config::default();
        c.fusion.adaptive.serve = vlmfuse_fusion::Serve::VoteFallback;
        c
    };
    let srv = Arc::new(TestApp::start(&tmp.path().join("c"), cfg()).await);

    // Phase 1: fuse everything from several clients (no feedback yet: order cannot matter).
    let fused: Arc<Mutex<BTreeMap<usize, Value>>> = Arc::default();
    {
        let (srv, fused, rounds) = (srv.clone(), fused.clone(), rounds.clone());
        in_parallel(n, move |i| {
            let (srv, fused, rounds) = (srv.clone(), fused.clone(), rounds.clone());
            async move {
                let mut r = rounds[i].clone();
                r.as_object_mut().unwrap().remove("truth");
                let resp = srv.post("/v1/fuse", &r).await;
                assert_eq!(resp.status, 200);
                fused.lock().unwrap().insert(i, resp.json());
            }
        })
        .await;
    }
    // Phase 2: label everything from several clients; the writer serialises the feedback.
    let labelled: Arc<Mutex<BTreeMap<u64, (usize, Value)>>> = Arc::default();
    {
        let (srv, fused, labelled, rounds) =
            (srv.clone(), fused.clone(), labelled.clone(), rounds.clone());
        in_parallel(n, move |i| {
            let (srv, fused, labelled, rounds) =
                (srv.clone(), fused.clone(), labelled.clone(), rounds.clone());
            async move {
                let id = fused.lock().unwrap()[&i]["round_id"].clone();
                let resp = srv
                    .post(
                        "/v1/feedback",
                        &json!({"round_id": id, "labels": rounds[i]["truth"]}),
                    )
                    .await;
                assert_eq!(resp.status, 200);
                let v = resp.json();
                let order = v["labelled_rounds"].as_u64().unwrap();
                assert!(
                    labelled.lock().unwrap().insert(order, (i, v)).is_none(),
                    "order {order} twice"
                );
            }
        })
        .await;
    }
    let labelled = labelled.lock().unwrap().clone();
    assert_eq!(labelled.len(), n);
    assert_eq!(*labelled.keys().last().unwrap(), n as u64);
    let state = srv.state().await;

    // The sequential replay: fuse in the same order of round ids, then label in the service's
    // labelling order.
    let seq = TestApp::start(&tmp.path().join("s"), cfg()).await;
    let fused = fused.lock().unwrap().clone();
    let mut by_id: Vec<(String, usize)> = fused
        .iter()
        .map(|(i, v)| (v["round_id"].as_str().unwrap().to_string(), *i))
        .collect();
    by_id.sort();
    for (id, i) in &by_id {
        let mut r = rounds[*i].clone();
        r.as_object_mut().unwrap().remove("truth");
        let resp = seq.post("/v1/fuse", &r).await;
        assert_eq!(resp.json()["round_id"], json!(id));
        assert_eq!(
            strip_ids(&resp.json()),
            strip_ids(&fused[i]),
            "fuse of round {i}"
        );
    }
    for (order, (i, v)) in &labelled {
        let resp = seq
            .post(
                "/v1/feedback",
                &json!({"round_id": fused[i]["round_id"], "labels": rounds[*i]["truth"]}),
            )
            .await;
        assert_eq!(
            &resp.json(),
            v,
            "feedback number {order} (round {i}) differs"
        );
    }
    assert_eq!(seq.state().await, state);
}
