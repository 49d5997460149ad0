//! The labeler as the service serves it: `POST /v1/label`, the labels `/v1/infer` gets, and the
//! claim that what is served is what `labeler_eval` measured.

use crate::support::TestApp;
use serde_json::{json, Value};
use vlmfuse_labeler::LabelerOutput;
use vlmfuse_testkit::server::{FakeOpenAi, LABELER_LABELS, LABELER_MODEL};
use vlmfuse_testkit_models::assets::{require_assets, AssetPaths};
use vlmfuse_testkit_models::labeler_eval::{
    default_dataset_path, eval_embedding_labeler, label_in_rounds, load_dataset,
    styles_dataset_path, test_split, ROUND_ANSWERS,
};

const SHIPPED: &str = include_str!("../../../../config/default.toml");

/// The fetched assets; panics, naming the fetch script, when they are missing.
fn assets() -> AssetPaths {
    require_assets()
}

/// The shipped configuration with a clip pipeline (one remote reporter), so that the labeler is
/// loaded at startup as `/v1/infer` uses it.
fn shipped_with_reporter(fake: &FakeOpenAi) -> String {
    format!("{SHIPPED}\n{}", fake.reporter_toml("vlaad", "frames"))
}

/// The labeler `config/default.toml` serves gives, answer for answer, the labels and evidence
/// that `labeler_eval` scores on the held-out test split, labelled in rounds as both label them.
#[tokio::test(flavor = "multi_thread")]
#[ignore = "needs assets: scripts/fetch-assets.sh"]
async fn the_served_labeler_is_the_evaluated_one() {
    let a = assets();
    // Both labelled sets' held-out parts: the first (mostly the paper's answer shape) and the
    // second (other styles).
    let first = load_dataset(&default_dataset_path()).unwrap();
    let second = load_dataset(&styles_dataset_path()).unwrap();
    assert!(test_split(&first).len() >= 250);
    assert!(test_split(&second).len() >= 150);
    let test: Vec<_> = test_split(&first)
        .into_iter()
        .chain(test_split(&second))
        .collect();
    let texts: Vec<&str> = test.iter().map(|e| e.text.as_str()).collect();
    let evaluated = label_in_rounds(&eval_embedding_labeler(&a).unwrap(), &texts).unwrap();

    let tmp = tempfile::tempdir().unwrap();
    let fake = FakeOpenAi::start();
    let srv = TestApp::from_toml(tmp.path(), &shipped_with_reporter(&fake)).await;
    let ready = srv.get("/readyz").await.json();
    assert_eq!(ready["status"], "ready", "{ready}");
    let mut served: Vec<LabelerOutput> = Vec::new();
    for round in texts.chunks(ROUND_ANSWERS) {
        let round: Vec<String> = round.iter().map(|t| t.to_string()).collect();
        served.extend(srv.state.service.label(&round).await.unwrap().outputs);
    }
    let differ: Vec<String> = test
        .iter()
        .zip(served.iter().zip(&evaluated))
        .filter(|(_, (s, e))| s.labels != e.labels || s.evidence != e.evidence)
        .map(|(ex, (s, e))| format!("{}: served {:?}, evaluated {:?}", ex.id, s.labels, e.labels))
        .collect();
    assert!(differ.is_empty(), "{}", differ.join("\n"));
    // And through HTTP, one round.
    let r = srv
        .post("/v1/label", &json!({"text": &texts[..ROUND_ANSWERS]}))
        .await;
    let v = r.json();
    assert_eq!(r.status, 200, "{v}");
    for (res, e) in v["results"].as_array().unwrap().iter().zip(&evaluated) {
        assert_eq!(res["labels"], json!(e.labels), "{v}");
    }
}

/// `config/default.toml` is the configuration the labelers were evaluated with: the paper's
/// labels with their glosses.
#[test]
fn the_shipped_ontology_has_the_evaluated_descriptions() {
    let cfg = vlmfuse::Config::from_toml(SHIPPED).unwrap();
    assert_eq!(cfg.ontology, vlmfuse_labeler::Ontology::default_driving());
    assert!(cfg
        .ontology
        .labels()
        .iter()
        .all(|l| l.description.is_some()));
}

/// A description written in the config reaches the labeler: the LLM labeler's prompt shows it.
/// Without a clip pipeline the labeler is not loaded at startup, and `/v1/label` loads it.
#[tokio::test(flavor = "multi_thread")]
async fn configured_descriptions_reach_the_labeler_loaded_on_first_use() {
    let tmp = tempfile::tempdir().unwrap();
    let fake = FakeOpenAi::start();
    let custom = "slowing down for any reason, including a queue (TEST GLOSS)";
    let cfg = SHIPPED.replace(
        "description = \"braking or slowing the vehicle down\"",
        &format!("description = {custom:?}"),
    );
    assert_ne!(cfg, SHIPPED);
    // The shipped file with its [labeler] table (the last one) swapped for the remote labeler.
    let cut = cfg.find("\n[labeler]\n").expect("the shipped [labeler]");
    let cfg = format!("{}\n{}", &cfg[..cut], fake.labeler_toml());
    let srv = TestApp::from_toml(tmp.path(), &cfg).await;
    // A /v1/fuse-only deployment: ready without the labeler.
    let ready = srv.get("/readyz").await;
    assert_eq!(ready.status, 200, "{}", ready.json());
    assert_eq!(fake.calls(LABELER_MODEL), 0);

    let r = srv
        .post("/v1/label", &json!({"text": "Brake for the queue."}))
        .await;
    let v = r.json();
    assert_eq!(r.status, 200, "{v}");
    assert_eq!(v["labeler"], format!("openai:{LABELER_MODEL}"), "{v}");
    assert_eq!(v["labels"], json!(LABELER_LABELS), "{v}");
    let system = fake.last_request(LABELER_MODEL).unwrap()["messages"][0]["content"]
        .as_str()
        .unwrap()
        .to_string();
    assert!(system.contains(&format!("- brake: {custom}")), "{system}");
    assert!(
        system.contains("- stop: bringing the vehicle to a complete stop"),
        "{system}"
    );
    // Every evidence names an ontology label and is an LLM's.
    for e in v["evidence"].as_array().unwrap() {
        assert_eq!(e["source"], "llm", "{v}");
        assert_eq!(e["accepted"], true, "{v}");
    }
    // The scores cover the ontology in order.
    let ids: Vec<&str> = v["scores"]
        .as_object()
        .unwrap()
        .keys()
        .map(String::as_str)
        .collect();
    assert_eq!(ids.len(), 14);
}

/// One text or a list; labels with evidence, discounted mentions shown.
#[tokio::test(flavor = "multi_thread")]
#[ignore = "needs assets: scripts/fetch-assets.sh"]
async fn label_route_returns_labels_with_evidence() {
    assets();
    let tmp = tempfile::tempdir().unwrap();
    let fake = FakeOpenAi::start();
    let srv = TestApp::from_toml(tmp.path(), &shipped_with_reporter(&fake)).await;
    let text = "No need to stop, just slow down. Be ready to turn left at the junction.";
    let r = srv.post("/v1/label", &json!({ "text": text })).await;
    let v = r.json();
    assert_eq!(r.status, 200, "{v}");
    assert!(
        v["labeler"].as_str().unwrap().starts_with("embedding:"),
        "{v}"
    );
    assert!(v["label_ms"].as_f64().unwrap() >= 0.0, "{v}");
    assert_eq!(v["labels"], json!(["brake", "junction_ahead"]), "{v}");
    let ev = |id: &str| -> Value {
        v["evidence"]
            .as_array()
            .unwrap()
            .iter()
            .find(|e| e["label"] == id)
            .cloned()
            .unwrap_or_else(|| panic!("no evidence for {id}: {v}"))
    };
    let brake = ev("brake");
    assert_eq!(
        (
            &brake["accepted"],
            &brake["source"],
            brake["clause"].as_str().unwrap()
        ),
        (
            &json!(true),
            &json!("rule"),
            "No need to stop, just slow down."
        ),
        "{brake}"
    );
    let stop = ev("stop");
    assert_eq!(
        (&stop["accepted"], &stop["negated"]),
        (&json!(false), &json!(true))
    );
    let left = ev("turn_left");
    assert_eq!(
        (&left["accepted"], &left["hedged"]),
        (&json!(false), &json!(true))
    );
    assert_eq!(v["scores"]["brake"], json!(1.0), "{v}");

    // A list: one result per text, in order; the same text labels the same either way.
    let r = srv
        .post(
            "/v1/label",
            &json!({"text": ["Stop at the red light.", text, ""]}),
        )
        .await;
    let b = r.json();
    assert_eq!(r.status, 200, "{b}");
    let results = b["results"].as_array().unwrap();
    assert_eq!(results.len(), 3);
    assert_eq!(results[0]["labels"], json!(["stop", "traffic_light_ahead"]));
    assert_eq!(results[1]["labels"], v["labels"]);
    assert_eq!(results[1]["evidence"], v["evidence"]);
    assert_eq!(results[2]["labels"], json!([]));
}

/// Bad bodies are refused with the reason, and nothing is labelled.
#[tokio::test(flavor = "multi_thread")]
async fn bad_label_requests_are_refused_clearly() {
    let tmp = tempfile::tempdir().unwrap();
    let fake = FakeOpenAi::start();
    // The OpenAI labeler against the fake server: no model assets needed for the refusals.
    let cfg = format!("[limits]\nmax_label_texts = 3\n\n{}", fake.labeler_toml());
    let srv = TestApp::from_toml(tmp.path(), &cfg).await;
    for (body, kind, says) in [
        (json!({}), "invalid_request", "missing field \"text\""),
        (json!({"text": []}), "invalid_request", "empty list"),
        (
            json!({"text": ["a", 3]}),
            "invalid_request",
            "text[1] is not a string",
        ),
        (
            json!({"text": {"a": 1}}),
            "invalid_request",
            "a string or a list",
        ),
        (
            json!({"text": "a", "lang": "en"}),
            "invalid_request",
            "unknown field \"lang\"",
        ),
        (json!(["a"]), "invalid_request", "JSON object"),
        (
            json!({"text": ["a", "b", "c", "d"]}),
            "invalid_request",
            "at most 3",
        ),
        (
            json!({"text": ["ok", "x".repeat(70_000)]}),
            "invalid_request",
            "text[1] has 70000 bytes",
        ),
    ] {
        let r = srv.post("/v1/label", &body).await;
        r.expect_error(422, kind);
        let msg = r.json()["error"].as_str().unwrap().to_string();
        assert!(msg.contains(says), "{body}: {msg}");
    }
    let r = srv
        .request(
            "POST",
            "/v1/label",
            &[("content-type", "application/json")],
            b"{\"text\": ".to_vec(),
        )
        .await;
    r.expect_error(400, "malformed_json");
    assert_eq!(fake.calls(LABELER_MODEL), 0, "nothing was labelled");

    // A labeler that cannot load is a 503 that says why, not a 500.
    let tmp2 = tempfile::tempdir().unwrap();
    let cfg = format!(
        "[labeler]\nkind = \"gguf\"\nmodel_path = {:?}\n",
        tmp2.path().join("missing.gguf")
    );
    let srv = TestApp::from_toml(tmp2.path(), &cfg).await;
    let r = srv.post("/v1/label", &json!({"text": "Brake."})).await;
    r.expect_error(503, "not_ready");
    assert!(
        r.json()["error"].to_string().contains("missing.gguf"),
        "{}",
        r.json()
    );

    // A remote labeler that keeps failing is a bad gateway.
    fake.kill(LABELER_MODEL);
    let tmp3 = tempfile::tempdir().unwrap();
    let srv = TestApp::from_toml(tmp3.path(), &fake.labeler_toml()).await;
    let r = srv.post("/v1/label", &json!({"text": "Brake."})).await;
    r.expect_error(502, "labeler_upstream");
}

/// With an API key, labelling (a model run) needs the bearer token like the other model routes.
#[tokio::test(flavor = "multi_thread")]
async fn label_needs_the_key_when_one_is_set() {
    let tmp = tempfile::tempdir().unwrap();
    let fake = FakeOpenAi::start();
    let cfg = format!("[server]\napi_key = \"k\"\n\n{}", fake.labeler_toml());
    let srv = TestApp::from_toml(tmp.path(), &cfg).await;
    let r = srv.post("/v1/label", &json!({"text": "Brake."})).await;
    r.expect_error(401, "unauthorized");
    let r = srv
        .request(
            "POST",
            "/v1/label",
            &[
                ("content-type", "application/json"),
                ("authorization", "Bearer k"),
            ],
            serde_json::to_vec(&json!({"text": "Brake."})).unwrap(),
        )
        .await;
    assert_eq!(r.status, 200, "{}", r.json());
}
