//! Concurrent clients get what a sequential replay in the server's arrival order gives: rounds
//! fused in parallel, then labelled from several threads at once, must produce the same credits,
//! reputations and final state as one client replaying the feedback in the labelling order the
//! server reported (`labelled_rounds` in each answer).

mod service_support;

use serde_json::{json, Value};
use service_support::*;
use std::collections::BTreeMap;
use std::sync::{Arc, Mutex};

const THREADS: usize = 8;

fn strip_ids(v: &Value) -> Value {
    let mut v = v.clone();
    v.as_object_mut().unwrap().remove("round_id");
    v.as_object_mut().unwrap().remove("id");
    v
}

#[test]
fn concurrent_feedback_equals_a_sequential_replay() {
    let tmp = tempfile::tempdir().unwrap();
    let rounds: Vec<Value> = generate_rounds(160, 16, 11)
        .into_iter()
        .filter(|r| r.get("truth").is_some())
        .collect();
    let srv = Arc::new(Server::start(&tmp.path().join("c"), &[], &[]));

    // Phase 1: fuse everything from several threads (no feedback yet: order cannot matter).
    let fused: Arc<Mutex<BTreeMap<usize, Value>>> = Arc::default();
    let work = |f: Arc<dyn Fn(usize) + Send + Sync>| {
        let hs: Vec<_> = (0..THREADS)
            .map(|t| {
                let f = f.clone();
                let n = rounds.len();
                std::thread::spawn(move || (t..n).step_by(THREADS).for_each(|i| f(i)))
            })
            .collect();
        hs.into_iter().for_each(|h| h.join().unwrap());
    };
    {
        let (srv, fused, rounds) = (srv.clone(), fused.clone(), rounds.clone());
        work(Arc::new(move |i| {
            let mut r = rounds[i].clone();
            r.as_object_mut().unwrap().remove("truth");
            let resp = srv.post("/v1/fuse", &r);
            assert_eq!(resp.status, 200);
            fused.lock().unwrap().insert(i, resp.json());
        }));
    }
    // Phase 2: label everything from several threads; the server serialises the feedback.
    let labelled: Arc<Mutex<BTreeMap<u64, (usize, Value)>>> = Arc::default();
    {
        let (srv, fused, labelled, rounds) =
            (srv.clone(), fused.clone(), labelled.clone(), rounds.clone());
        work(Arc::new(move |i| {
            let id = fused.lock().unwrap()[&i]["round_id"].clone();
            let resp = srv.post(
                "/v1/feedback",
                &json!({"round_id": id, "labels": rounds[i]["truth"]}),
            );
            assert_eq!(resp.status, 200);
            let v = resp.json();
            let order = v["labelled_rounds"].as_u64().unwrap();
            assert!(
                labelled.lock().unwrap().insert(order, (i, v)).is_none(),
                "order {order} twice"
            );
        }));
    }
    let labelled = labelled.lock().unwrap().clone();
    assert_eq!(labelled.len(), rounds.len());
    assert_eq!(*labelled.keys().last().unwrap(), rounds.len() as u64);
    let state = srv.state();

    // The sequential replay: fuse in the same order of round ids, then label in the server's
    // labelling order.
    let seq = Server::start(&tmp.path().join("s"), &[], &[]);
    let fused = fused.lock().unwrap().clone();
    let mut by_id: Vec<(String, usize)> = fused
        .iter()
        .map(|(i, v)| (v["round_id"].as_str().unwrap().to_string(), *i))
        .collect();
    by_id.sort();
    for (id, i) in &by_id {
        let mut r = rounds[*i].clone();
        r.as_object_mut().unwrap().remove("truth");
        let resp = seq.post("/v1/fuse", &r);
        assert_eq!(resp.json()["round_id"], json!(id));
        assert_eq!(
            strip_ids(&resp.json()),
            strip_ids(&fused[i]),
            "fuse of round {i}"
        );
    }
    for (order, (i, v)) in &labelled {
        let resp = seq.post(
            "/v1/feedback",
            &json!({"round_id": fused[i]["round_id"], "labels": rounds[*i]["truth"]}),
        );
        assert_eq!(
            &resp.json(),
            v,
            "feedback number {order} (round {i}) differs"
        );
    }
    assert_eq!(seq.state(), state);
}
