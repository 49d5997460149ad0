//! Partial feedback on `/v1/feedback`: truth for a subset of labels (`known`) from a named
//! `source`, merged per round; a person's label overrides a derived one; repeats are
//! idempotent; rejected requests change nothing; and a replay of the database (what a restart
//! after kill -9 does) gives the very engine the service holds.

use crate::support::{Resp, TestApp};
use serde_json::{json, Value};
use vlmfuse::Config;
use vlmfuse_fusion::{Engine, Method};

fn round(ctx: &[f64], a: &[&str], b: &[&str], c: &[&str]) -> Value {
    json!({"context": ctx, "reports": {"vlaad": a, "videollama2": b, "videollava": c}})
}

async fn fuse(srv: &TestApp, ctx: &[f64]) -> String {
    let r = srv
        .post(
            "/v1/fuse",
            &round(ctx, &["brake"], &["brake", "stop"], &["turn_left"]),
        )
        .await;
    assert_eq!(r.status, 200, "{}", r.json());
    r.json()["round_id"].as_str().unwrap().to_string()
}

async fn counts(srv: &TestApp) -> (Value, (u64, u64)) {
    let store = vlmfuse_store::Store::open_read_only(&srv.data_dir).unwrap();
    (srv.state().await, store.counts().unwrap())
}

fn keys(v: &Value) -> Vec<String> {
    v.as_object().unwrap().keys().cloned().collect()
}

async fn partial_feedback_merges_per_label(method: Method) {
    let tmp = tempfile::tempdir().unwrap();
    let mut cfg = Config::default();
    cfg.fusion.method = method;
    let srv = TestApp::start(tmp.path(), cfg).await;
    let id = fuse(&srv, &[1.0, 0.2, 0.1]).await;

    // The vehicle's signals settle three labels.
    let r = srv
        .post(
            "/v1/feedback",
            &json!({"round_id": id, "labels": ["brake", "stop"],
                    "known": ["brake", "stop", "turn_left"], "source": "kinematics"}),
        )
        .await;
    assert_eq!(r.status, 200, "{}", r.json());
    let v = r.json();
    assert_eq!(v["labels"], json!(["brake", "stop"]));
    assert_eq!(
        v["learned"],
        json!({"turn_left": false, "brake": true, "stop": true})
    );
    assert_eq!(v["known"]["brake"], "kinematics");
    assert_eq!(v["unknown"].as_array().unwrap().len(), 11);
    assert_eq!(v["source"], "kinematics");
    assert_eq!(v["labelled_rounds"], 1);
    // Credit only on the three known labels: still efficient.
    let phi: f64 = v["shapley"]
        .as_object()
        .unwrap()
        .values()
        .map(|x| x.as_f64().unwrap())
        .sum();
    assert!((phi - v["value"].as_f64().unwrap()).abs() < 1e-9, "{v}");

    // The same again: nothing new, flagged, nothing stored.
    let before = counts(&srv).await;
    let again = srv
        .post(
            "/v1/feedback",
            &json!({"round_id": id, "labels": ["brake", "stop"],
                    "known": ["brake", "stop", "turn_left"], "source": "kinematics"}),
        )
        .await;
    assert_eq!(again.status, 200, "{}", again.json());
    assert_eq!(again.header("x-vlmfuse-repeated"), Some("true"));
    // The first answer again.
    assert_eq!(again.json(), v);
    assert_eq!(counts(&srv).await, before);

    // A derived source contradicting a derived source: 409, nothing stored.
    let clash = srv
        .post(
            "/v1/feedback",
            &json!({"round_id": id, "labels": [], "known": ["brake"], "source": "detector"}),
        )
        .await;
    assert_eq!(clash.status, 409, "{}", clash.json());
    assert_eq!(clash.json()["kind"], "conflict");
    assert!(clash.json()["error"].as_str().unwrap().contains("brake"));
    assert_eq!(counts(&srv).await, before);

    // A person: two new labels, and an override of a derived one (stop was wrong).
    let r = srv
        .post(
            "/v1/feedback",
            &json!({"round_id": id, "labels": ["brake", "junction_ahead"],
                    "known": ["stop", "junction_ahead", "merge"]}),
        )
        .await;
    // `brake` is in labels but not in known: refused, nothing stored.
    assert_eq!(r.status, 422, "{}", r.json());
    assert!(r.json()["error"].as_str().unwrap().contains("\"brake\""));
    assert_eq!(counts(&srv).await, before);
    let r = srv
        .post(
            "/v1/feedback",
            &json!({"round_id": id, "labels": ["junction_ahead"],
                    "known": ["stop", "junction_ahead", "merge"]}),
        )
        .await;
    assert_eq!(r.status, 200, "{}", r.json());
    let v = r.json();
    assert_eq!(v["labels"], json!(["brake", "junction_ahead"]));
    assert_eq!(
        v["learned"],
        json!({"stop": false, "junction_ahead": true, "merge": false})
    );
    assert_eq!(v["known"]["stop"], "human");
    assert_eq!(v["known"]["brake"], "kinematics");
    assert_eq!(v["source"], "human");
    assert_eq!(v["labelled_rounds"], 2);

    // Derived labels after a person's: hers stand, the rest is learned.
    let r = srv
        .post(
            "/v1/feedback",
            &json!({"round_id": id, "labels": ["stop", "traffic_light_ahead"],
                    "known": ["stop", "traffic_light_ahead"], "source": "detector"}),
        )
        .await;
    assert_eq!(r.status, 200, "{}", r.json());
    let v = r.json();
    assert_eq!(v["learned"], json!({"traffic_light_ahead": true}));
    assert_eq!(v["ignored"][0]["label"], "stop");
    assert!(v["labels"]
        .as_array()
        .unwrap()
        .contains(&json!("traffic_light_ahead")));
    assert!(!v["labels"].as_array().unwrap().contains(&json!("stop")));

    // Two people disagreeing: 409.
    let before = counts(&srv).await;
    let clash = srv
        .post(
            "/v1/feedback",
            &json!({"round_id": id, "labels": ["merge"], "known": ["merge"]}),
        )
        .await;
    assert_eq!(clash.status, 409, "{}", clash.json());
    assert_eq!(counts(&srv).await, before);

    // Bad requests change nothing either.
    for (body, needle) in [
        (
            json!({"round_id": id, "labels": [], "known": []}),
            "\"known\" is empty",
        ),
        (
            json!({"round_id": id, "labels": [], "known": ["merge"], "source": ""}),
            "\"source\"",
        ),
        (
            json!({"round_id": id, "labels": [], "known": ["merge"], "source": "a b"}),
            "\"source\"",
        ),
        (
            json!({"round_id": id, "labels": [], "known": ["fly"]}),
            "fly",
        ),
    ] {
        let r: Resp = srv.post("/v1/feedback", &body).await;
        assert_eq!(r.status, 422, "{body}: {}", r.json());
        assert!(
            r.json()["error"].as_str().unwrap().contains(needle),
            "{body}: {}",
            r.json()
        );
        assert_eq!(counts(&srv).await, before, "{body}");
    }

    // A full feedback on another round, as before partial feedback existed.
    let id2 = fuse(&srv, &[0.9, 0.3, 0.1]).await;
    let r = srv
        .post(
            "/v1/feedback",
            &json!({"round_id": id2, "labels": ["brake"]}),
        )
        .await;
    assert_eq!(r.status, 200, "{}", r.json());
    assert_eq!(r.json()["unknown"], json!([]));
    assert_eq!(keys(&r.json()["learned"]).len(), 14);

    // What a restart does: replay the database into a fresh engine. It must be the engine the
    // service holds: the same reputations to the bit, and the same posteriors for a new round.
    let cfg = Config {
        fusion: vlmfuse_fusion::FusionConfig {
            method,
            ..Config::default().fusion
        },
        ..Config::default()
    };
    let mut fresh = Engine::new(
        cfg.fusion.clone(),
        cfg.ontology.clone(),
        cfg.reporters.clone(),
    )
    .unwrap();
    let mut store = vlmfuse_store::Store::open_read_only(&srv.data_dir).unwrap();
    store.load_engine_full(&mut fresh).unwrap();
    assert_eq!(fresh.labelled(), 4);
    let st = srv.state().await;
    for (name, w) in fresh.reporters().iter().zip(fresh.reputations()) {
        assert_eq!(st["reputations"][name].as_f64().unwrap(), *w, "{name}");
    }
    let probe = round(&[0.95, 0.25, 0.1], &["brake"], &["stop"], &["brake"]);
    let rec: vlmfuse_fusion::RoundRecord = serde_json::from_value(probe.clone()).unwrap();
    let (r, _) = fresh.parse(&rec).unwrap();
    let q = fresh.infer(&r).q;
    let served = srv.post("/v1/fuse", &probe).await.json();
    for (k, label) in cfg.ontology.labels().iter().enumerate() {
        assert_eq!(
            served["posteriors"][&label.id].as_f64().unwrap(),
            q[k],
            "{}",
            label.id
        );
    }
}

#[tokio::test(flavor = "multi_thread")]
async fn partial_feedback_merges_per_label_under_adaptive() {
    partial_feedback_merges_per_label(Method::Adaptive).await;
}

#[tokio::test(flavor = "multi_thread")]
async fn partial_feedback_merges_per_label_under_paper() {
    partial_feedback_merges_per_label(Method::Paper).await;
}
