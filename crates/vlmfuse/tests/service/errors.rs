//! Every bad input gets its documented status and `{"error", "kind"}` body, and leaves the state
//! (as `/v1/state` and the database show it) untouched. Also auth, limits, overload and timeout
//! (in-process; the graceful shutdown on SIGTERM is in the `process` tests).

use crate::support::{Resp, TestApp};
use serde_json::{json, Value};
use std::time::Duration;
use vlmfuse::Config;

const KEY: &str = "s3cret-token";

fn round(ctx: &[f64]) -> Value {
    json!({"context": ctx, "reports": {"vlaad": ["brake"], "videollava": ["brake", "stop"]}})
}

async fn authed(srv: &TestApp, method: &str, path: &str, body: &[u8], ctype: &str) -> Resp {
    srv.request(
        method,
        path,
        &[
            ("content-type", ctype),
            ("authorization", &format!("Bearer {KEY}")),
        ],
        body.to_vec(),
    )
    .await
}

async fn post_json(srv: &TestApp, path: &str, v: &Value) -> Resp {
    authed(
        srv,
        "POST",
        path,
        &serde_json::to_vec(v).unwrap(),
        "application/json",
    )
    .await
}

async fn raw(srv: &TestApp, path: &str, body: &str) -> Resp {
    authed(srv, "POST", path, body.as_bytes(), "application/json").await
}

/// The state through the API and the row counts in the database.
async fn snapshot(srv: &TestApp) -> (Value, (u64, u64)) {
    // Read-only: the running service holds the data directory's lock.
    let store = vlmfuse_store::Store::open_read_only(&srv.data_dir).unwrap();
    (srv.state().await, store.counts().unwrap())
}

#[tokio::test(flavor = "multi_thread")]
async fn bad_inputs_are_refused_and_change_nothing() {
    let tmp = tempfile::tempdir().unwrap();
    let mut cfg = Config::default();
    cfg.server.api_key = Some(KEY.into());
    cfg.limits.max_body_bytes = 4096;
    cfg.limits.max_batch_rounds = 4;
    cfg.limits.max_context_dim = 8;
    let srv = TestApp::start(tmp.path(), cfg).await;
    // Some state to protect: two rounds, one labelled.
    let r0 = post_json(&srv, "/v1/fuse", &round(&[1.0, 0.0, 0.5, 0.2])).await;
    assert_eq!(r0.status, 200, "{:?}", r0.json());
    let id0 = r0.json()["round_id"].as_str().unwrap().to_string();
    assert_eq!(id0, "r-00000000");
    let fb0 = post_json(
        &srv,
        "/v1/feedback",
        &json!({"round_id": id0, "labels": ["brake"]}),
    )
    .await;
    assert_eq!(fb0.status, 200, "{:?}", fb0.json());
    let r1 = post_json(&srv, "/v1/fuse", &round(&[0.0, 1.0, 0.5, 0.2])).await;
    let id1 = r1.json()["round_id"].as_str().unwrap().to_string();
    let before = snapshot(&srv).await;
    assert_eq!(before.1, (2, 1));

    let cases: Vec<(&str, Resp, u16, &str)> = vec![
        (
            "malformed JSON",
            raw(&srv, "/v1/fuse", "{\"context\": [1, 2").await,
            400,
            "malformed_json",
        ),
        (
            "NaN literal",
            raw(
                &srv,
                "/v1/fuse",
                r#"{"context": [NaN, 1, 1, 1], "reports": {"vlaad": []}}"#,
            ).await,
            400,
            "malformed_json",
        ),
        (
            "number out of range",
            raw(
                &srv,
                "/v1/fuse",
                r#"{"context": [1e999, 1, 1, 1], "reports": {"vlaad": []}}"#,
            ).await,
            400,
            "malformed_json",
        ),
        (
            "zero context",
            post_json(&srv, "/v1/fuse", &round(&[0.0, 0.0, 0.0, 0.0])).await,
            422,
            "bad_context",
        ),
        (
            "context of strings",
            post_json(
                &srv,
                "/v1/fuse",
                &json!({"context": ["a"], "reports": {"vlaad": []}}),
            ).await,
            422,
            "invalid_request",
        ),
        (
            "not an object",
            post_json(&srv, "/v1/fuse", &json!([1, 2])).await,
            422,
            "invalid_request",
        ),
        (
            "wrong dimension",
            post_json(&srv, "/v1/fuse", &round(&[1.0, 0.0, 0.5])).await,
            422,
            "dimension_mismatch",
        ),
        (
            "unknown reporter",
            post_json(
                &srv,
                "/v1/fuse",
                &json!({"context": [1, 0, 0, 0], "reports": {"gpt": ["brake"]}}),
            ).await,
            422,
            "unknown_reporter",
        ),
        (
            "unknown label",
            post_json(
                &srv,
                "/v1/fuse",
                &json!({"context": [1, 0, 0, 0], "reports": {"vlaad": ["fly"]}}),
            ).await,
            422,
            "unknown_label",
        ),
        (
            "empty coalition",
            post_json(
                &srv,
                "/v1/fuse",
                &json!({"context": [1, 0, 0, 0], "reports": {}}),
            ).await,
            422,
            "empty_coalition",
        ),
        (
            "truth on fuse",
            post_json(
                &srv,
                "/v1/fuse",
                &json!({"context": [1, 0, 0, 0], "reports": {"vlaad": []}, "truth": ["brake"]}),
            ).await,
            422,
            "truth_not_accepted",
        ),
        (
            "misspelled field on fuse",
            post_json(
                &srv,
                "/v1/fuse",
                &json!({"context": [1, 0, 0, 0], "reports": {"vlaad": []}, "requestId": "k1"}),
            ).await,
            422,
            "invalid_request",
        ),
        (
            "unknown field on fuse",
            post_json(
                &srv,
                "/v1/fuse",
                &json!({"context": [1, 0, 0, 0], "reports": {"vlaad": []}, "truths": ["brake"]}),
            ).await,
            422,
            "invalid_request",
        ),
        (
            "unknown field in a batch round",
            post_json(
                &srv,
                "/v1/fuse",
                &json!({"rounds": [{"context": [1, 0, 0, 0], "reports": {"vlaad": []}, "idempotency_key": "k"}]}),
            ).await,
            422,
            "invalid_request",
        ),
        (
            "context over max_context_dim",
            post_json(&srv, "/v1/fuse", &round(&[0.5; 9])).await,
            422,
            "invalid_request",
        ),
        (
            "one bad round in a batch",
            post_json(
                &srv,
                "/v1/fuse",
                &json!({"rounds": [round(&[1.0, 0.0, 0.0, 0.0]), {"context": [1, 0, 0, 0], "reports": {"vlaad": ["fly"]}}]}),
            ).await,
            422,
            "unknown_label",
        ),
        (
            "batch of mixed dimensions",
            post_json(
                &srv,
                "/v1/fuse",
                &json!({"rounds": [round(&[1.0, 0.0, 0.0, 0.0]), round(&[1.0, 0.0])]}),
            ).await,
            422,
            "dimension_mismatch",
        ),
        (
            "batch over the limit",
            post_json(
                &srv,
                "/v1/fuse",
                &json!({"rounds": vec![round(&[1.0, 0.0, 0.0, 0.0]); 5]}),
            ).await,
            422,
            "invalid_request",
        ),
        (
            "empty batch",
            post_json(&srv, "/v1/fuse", &json!({"rounds": []})).await,
            422,
            "invalid_request",
        ),
        (
            "wrong content type",
            authed(&srv, "POST", "/v1/fuse", b"{}", "text/plain").await,
            415,
            "unsupported_media_type",
        ),
        (
            "body too large",
            post_json(&srv, "/v1/fuse", &round(&vec![0.5; 2000])).await,
            413,
            "payload_too_large",
        ),
        (
            "no token",
            srv.request(
                "POST",
                "/v1/fuse",
                &[("content-type", "application/json")],
                serde_json::to_vec(&round(&[1.0, 0.0, 0.0, 0.0])).unwrap(),
            )
            .await,
            401,
            "unauthorized",
        ),
        (
            "wrong token",
            srv.request(
                "POST",
                "/v1/feedback",
                &[
                    ("content-type", "application/json"),
                    ("authorization", "Bearer nope"),
                ],
                br#"{"round_id": "r-00000001", "labels": []}"#.to_vec(),
            )
            .await,
            401,
            "unauthorized",
        ),
        (
            "unknown round",
            post_json(
                &srv,
                "/v1/feedback",
                &json!({"round_id": "r-00000099", "labels": []}),
            ).await,
            404,
            "unknown_round",
        ),
        (
            "non-canonical round id",
            post_json(
                &srv,
                "/v1/feedback",
                &json!({"round_id": "r-1", "labels": []}),
            ).await,
            404,
            "unknown_round",
        ),
        (
            "feedback unknown label",
            post_json(
                &srv,
                "/v1/feedback",
                &json!({"round_id": id1, "labels": ["fly"]}),
            ).await,
            422,
            "unknown_label",
        ),
        (
            "feedback extra field",
            post_json(
                &srv,
                "/v1/feedback",
                &json!({"round_id": id1, "labels": [], "truth": []}),
            ).await,
            422,
            "invalid_request",
        ),
        (
            "feedback missing labels",
            post_json(&srv, "/v1/feedback", &json!({"round_id": id1})).await,
            422,
            "invalid_request",
        ),
        (
            "conflicting feedback",
            post_json(
                &srv,
                "/v1/feedback",
                &json!({"round_id": id0, "labels": ["stop"]}),
            ).await,
            409,
            "conflict",
        ),
        ("unknown route", srv.get("/v2/nothing").await, 404, "not_found"),
        (
            "wrong method",
            srv.get("/v1/fuse").await,
            405,
            "method_not_allowed",
        ),
        (
            "infer not configured",
            authed(
                &srv,
                "POST",
                "/v1/infer",
                b"",
                "multipart/form-data; boundary=x",
            ).await,
            503,
            "not_ready",
        ),
    ];
    for (what, resp, status, kind) in &cases {
        let v = resp.json();
        assert_eq!(resp.status, *status, "{what}: {v}");
        assert_eq!(v["kind"], *kind, "{what}: {v}");
        assert!(
            v["error"].as_str().is_some_and(|s| !s.is_empty()),
            "{what}: {v}"
        );
        assert_eq!(snapshot(&srv).await, before, "{what} changed the state");
    }
    assert!(cases[cases.len() - 1].1.json()["error"]
        .as_str()
        .unwrap()
        .contains("clip ingestion is not configured"));

    // The same labels again: the first answer, flagged, and nothing changes.
    let again = post_json(
        &srv,
        "/v1/feedback",
        &json!({"round_id": id0, "labels": ["brake"]}),
    )
    .await;
    assert_eq!(again.status, 200);
    assert_eq!(again.header("x-vlmfuse-repeated"), Some("true"));
    assert_eq!(again.json(), fb0.json());
    // Display names name the same labels.
    let again = post_json(
        &srv,
        "/v1/feedback",
        &json!({"round_id": id0, "labels": ["brake", "brake"]}),
    )
    .await;
    assert_eq!(again.json(), fb0.json());
    assert_eq!(snapshot(&srv).await, before);

    // The metrics saw all of it.
    let m = String::from_utf8(srv.get("/metrics").await.body).unwrap();
    for name in [
        "vlmfuse_http_requests_total{",
        "vlmfuse_http_request_duration_seconds_bucket{",
        "vlmfuse_fusion_duration_seconds_bucket",
        "vlmfuse_feedback_duration_seconds_bucket",
        "vlmfuse_reputation{reporter=\"vlaad\"}",
        "vlmfuse_labelled_rounds 1",
        "vlmfuse_threshold ",
        "vlmfuse_rejected_requests_total{kind=\"unknown_label\"}",
        "vlmfuse_rejected_requests_total{kind=\"conflict\"}",
    ] {
        assert!(m.contains(name), "/metrics lacks {name}:\n{m}");
    }
    assert!(m.contains("route=\"/v1/fuse\""), "{m}");

    // Reads need no token; probes answer.
    assert_eq!(srv.get("/healthz").await.status, 200);
    assert_eq!(srv.get("/readyz").await.json()["status"], "ready");
    assert_eq!(
        srv.get("/v1/ontology").await.json()["labels"]
            .as_array()
            .unwrap()
            .len(),
        14
    );
    let spec = srv.get("/openapi.yaml").await;
    assert_eq!(spec.status, 200);
    assert!(String::from_utf8(spec.body)
        .unwrap()
        .starts_with("openapi:"));
}

/// With a concurrency limit of 1 and slow fuse requests (the service's test hook), a second
/// request is refused with 429 at once; probes are not limited; a request over the timeout gets
/// 503 and stores nothing, and a restart keeps what was stored.
#[tokio::test(flavor = "multi_thread")]
async fn overload_is_refused_at_once_and_a_timeout_stores_nothing() {
    let tmp = tempfile::tempdir().unwrap();
    let mut cfg = Config::default();
    cfg.limits.concurrency_limit = 1;
    cfg.limits.request_timeout_s = 2.0;
    let srv = std::sync::Arc::new(TestApp::start(tmp.path(), cfg).await);
    srv.state
        .service
        .test_hooks()
        .set_fuse_delay(Duration::from_millis(1000));
    let body = serde_json::to_vec(&round(&[1.0, 0.0, 0.5, 0.2])).unwrap();
    let json_ct = [("content-type", "application/json")];
    let before = srv.state().await;
    let slow = {
        let (srv, body) = (srv.clone(), body.clone());
        tokio::spawn(async move {
            srv.request(
                "POST",
                "/v1/fuse",
                &[("content-type", "application/json")],
                body,
            )
            .await
        })
    };
    tokio::time::sleep(Duration::from_millis(300)).await;
    // Reads are behind the limit too.
    srv.get("/v1/state").await.expect_error(429, "overloaded");
    let refused = srv
        .request("POST", "/v1/fuse", &json_ct, body.clone())
        .await;
    refused.expect_error(429, "overloaded");
    assert_eq!(refused.header("retry-after"), Some("1"));
    // Probes are not behind the limit.
    assert_eq!(srv.get("/healthz").await.status, 200);
    assert_eq!(slow.await.unwrap().status, 200);
    // The slow round was stored, the refused one was not.
    assert_eq!(
        srv.state().await["rounds"],
        before["rounds"].as_u64().unwrap() + 1
    );
    let m = String::from_utf8(srv.get("/metrics").await.body).unwrap();
    assert!(m.contains("vlmfuse_overload_total 2"), "{m}");
    drop(srv);

    // Timeout: the fuse takes 1 s against a 0.5 s budget; the restarted service kept the round.
    let mut cfg = Config::default();
    cfg.limits.request_timeout_s = 0.5;
    let srv = TestApp::start(tmp.path(), cfg).await;
    srv.state
        .service
        .test_hooks()
        .set_fuse_delay(Duration::from_millis(1000));
    assert_eq!(srv.state().await["rounds"], 1);
    let r = srv.request("POST", "/v1/fuse", &json_ct, body).await;
    r.expect_error(503, "timeout");
    assert_eq!(
        srv.state().await["rounds"],
        1,
        "a timed-out fuse stored its round"
    );
}
