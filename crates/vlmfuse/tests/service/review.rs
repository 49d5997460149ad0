//! `GET /v1/review`: the queue lists the rounds that stand for the unlabelled traffic, never a
//! fully labelled one, a partly labelled one with its unknown labels only; bad queries are
//! refused; and reading it changes nothing.

use crate::support::TestApp;
use serde_json::{json, Value};
use vlmfuse::Config;

/// A round in scene `a` (contexts near the first axis) or scene `b` (near the second); in scene
/// `b` the reporters split on `brake`.
fn round(t: usize, scene_b: bool) -> Value {
    let wobble = (t % 5) as f64 * 0.02;
    let ctx = if scene_b {
        vec![wobble, 1.0, 0.1, 0.0]
    } else {
        vec![1.0, wobble, 0.0, 0.1]
    };
    let (good, bad): (Vec<&str>, Vec<&str>) = if scene_b {
        (vec!["brake"], vec![])
    } else {
        (vec!["stop"], vec!["stop"])
    };
    json!({"id": format!("clip-{t}"), "context": ctx,
           "reports": {"vlaad": good, "videollama2": good, "videollava": bad}})
}

async fn fuse(srv: &TestApp, body: Value) -> String {
    let r = srv.post("/v1/fuse", &body).await;
    assert_eq!(r.status, 200, "{:?}", r.json());
    r.json()["round_id"].as_str().unwrap().to_string()
}

#[tokio::test]
async fn the_queue_asks_for_the_unlabelled_scene_and_changes_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let srv = TestApp::start(dir.path(), Config::default()).await;
    let empty = srv.get("/v1/review").await;
    assert_eq!(empty.status, 200, "{:?}", empty.json());
    assert_eq!(empty.json()["queue"], json!([]));

    // Scene a: eight rounds, all but one labelled in full; that one partly (stop known).
    let mut a_ids = Vec::new();
    for t in 0..8 {
        a_ids.push(fuse(&srv, round(t, false)).await);
    }
    for id in &a_ids[..7] {
        let f = srv
            .post("/v1/feedback", &json!({"round_id": id, "labels": ["stop"]}))
            .await;
        assert_eq!(f.status, 200, "{:?}", f.json());
    }
    let f = srv
        .post(
            "/v1/feedback",
            &json!({"round_id": a_ids[7], "labels": ["stop"], "known": ["stop"]}),
        )
        .await;
    assert_eq!(f.status, 200, "{:?}", f.json());
    // Scene b: six rounds nobody has labelled.
    let mut b_ids = Vec::new();
    for t in 0..6 {
        b_ids.push(fuse(&srv, round(t, true)).await);
    }

    let state_before = srv.state().await;
    let r = srv.get("/v1/review?limit=3").await;
    assert_eq!(r.status, 200, "{:?}", r.json());
    let v = r.json();
    assert_eq!(v["considered"], 14);
    assert_eq!(v["labelled"], 7);
    assert_eq!(v["candidates"], 7);
    let queue = v["queue"].as_array().unwrap();
    assert_eq!(queue.len(), 3);
    // First the unlabelled scene, which it stands for whole; the reporters split on brake there.
    let first = &queue[0];
    assert!(b_ids.contains(&first["round_id"].as_str().unwrap().to_string()));
    assert!(first["represents"].as_u64().unwrap() >= 6, "{first}");
    assert_eq!(first["disputed"], json!(["brake"]));
    assert!(first["novelty"].as_f64().unwrap() > 0.5, "{first}");
    assert!(!first["reasons"].as_array().unwrap().is_empty());
    // No fully labelled round is listed; the partly labelled one, if listed, without stop.
    for item in queue {
        let id = item["round_id"].as_str().unwrap().to_string();
        assert!(!a_ids[..7].contains(&id), "{item}");
        if id == a_ids[7] {
            let unknown = item["unknown"].as_array().unwrap();
            assert!(!unknown.contains(&json!("stop")), "{item}");
            assert_eq!(unknown.len(), 13);
        }
    }
    // Scores fall along the queue.
    let scores: Vec<f64> = queue.iter().map(|i| i["score"].as_f64().unwrap()).collect();
    assert!(scores.windows(2).all(|w| w[0] >= w[1]), "{scores:?}");
    assert_eq!(srv.state().await, state_before);
}

#[tokio::test]
async fn bad_review_queries_are_refused_and_change_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let srv = TestApp::start(dir.path(), Config::default()).await;
    fuse(&srv, round(0, true)).await;
    let before = srv.state().await;
    for (path, status) in [
        ("/v1/review?limit=0", 422),
        ("/v1/review?limit=101", 422),
        ("/v1/review?window=0", 422),
        ("/v1/review?window=2001", 422),
        ("/v1/review?limit=many", 400),
        ("/v1/review?order=desc", 400),
    ] {
        let r = srv.get(path).await;
        assert_eq!(r.status, status, "{path}: {:?}", r.json());
        assert!(r.json()["error"].as_str().is_some_and(|s| !s.is_empty()));
    }
    assert_eq!(srv.state().await, before);
    let ok = srv.get("/v1/review?limit=1&window=1").await;
    assert_eq!(ok.status, 200);
    assert_eq!(ok.json()["queue"].as_array().unwrap().len(), 1);
}
