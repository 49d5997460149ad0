//! Every bad input gets its documented status and `{"error", "kind"}` body, and leaves the state
//! (as `/v1/state` and the database show it) untouched. Also auth, limits, overload, timeout and
//! graceful shutdown.

mod service_support;

use serde_json::{json, Value};
use service_support::*;
use std::time::Duration;

const KEY: &str = "s3cret-token";

fn round(ctx: &[f64]) -> Value {
    json!({"context": ctx, "reports": {"vlaad": ["brake"], "videollava": ["brake", "stop"]}})
}

fn authed(srv: &Server, method: &str, path: &str, body: &[u8], ctype: &str) -> Resp {
    request(
        &srv.addr,
        method,
        path,
        &[
            ("content-type", ctype),
            ("authorization", &format!("Bearer {KEY}")),
        ],
        Some(body),
    )
    .unwrap()
}

fn post_json(srv: &Server, path: &str, v: &Value) -> Resp {
    authed(
        srv,
        "POST",
        path,
        &serde_json::to_vec(v).unwrap(),
        "application/json",
    )
}

/// The state through the API and the row counts in the database.
fn snapshot(srv: &Server) -> (Value, (u64, u64)) {
    let store = vlmfuse_store::Store::open(&srv.data_dir).unwrap();
    (srv.state(), store.counts().unwrap())
}

#[test]
fn bad_inputs_are_refused_and_change_nothing() {
    let tmp = tempfile::tempdir().unwrap();
    let srv = Server::start(
        tmp.path(),
        &[
            "--api-key",
            KEY,
            "--max-body-bytes",
            "4096",
            "--max-batch-rounds",
            "4",
        ],
        &[],
    );
    // Some state to protect: two rounds, one labelled.
    let r0 = post_json(&srv, "/v1/fuse", &round(&[1.0, 0.0, 0.5, 0.2]));
    assert_eq!(r0.status, 200, "{:?}", r0.json());
    let id0 = r0.json()["round_id"].as_str().unwrap().to_string();
    assert_eq!(id0, "r-00000000");
    let fb0 = post_json(
        &srv,
        "/v1/feedback",
        &json!({"round_id": id0, "labels": ["brake"]}),
    );
    assert_eq!(fb0.status, 200, "{:?}", fb0.json());
    let r1 = post_json(&srv, "/v1/fuse", &round(&[0.0, 1.0, 0.5, 0.2]));
    let id1 = r1.json()["round_id"].as_str().unwrap().to_string();
    let before = snapshot(&srv);
    assert_eq!(before.1, (2, 1));

    let raw = |srv: &Server, path: &str, body: &str| {
        authed(srv, "POST", path, body.as_bytes(), "application/json")
    };
    let cases: Vec<(&str, Resp, u16, &str)> = vec![
        (
            "malformed JSON",
            raw(&srv, "/v1/fuse", "{\"context\": [1, 2"),
            400,
            "malformed_json",
        ),
        (
            "NaN literal",
            raw(
                &srv,
                "/v1/fuse",
                r#"{"context": [NaN, 1, 1, 1], "reports": {"vlaad": []}}"#,
            ),
            400,
            "malformed_json",
        ),
        (
            "number out of range",
            raw(
                &srv,
                "/v1/fuse",
                r#"{"context": [1e999, 1, 1, 1], "reports": {"vlaad": []}}"#,
            ),
            400,
            "malformed_json",
        ),
        (
            "zero context",
            post_json(&srv, "/v1/fuse", &round(&[0.0, 0.0, 0.0, 0.0])),
            422,
            "bad_context",
        ),
        (
            "context of strings",
            post_json(
                &srv,
                "/v1/fuse",
                &json!({"context": ["a"], "reports": {"vlaad": []}}),
            ),
            422,
            "invalid_request",
        ),
        (
            "not an object",
            post_json(&srv, "/v1/fuse", &json!([1, 2])),
            422,
            "invalid_request",
        ),
        (
            "wrong dimension",
            post_json(&srv, "/v1/fuse", &round(&[1.0, 0.0, 0.5])),
            422,
            "dimension_mismatch",
        ),
        (
            "unknown reporter",
            post_json(
                &srv,
                "/v1/fuse",
                &json!({"context": [1, 0, 0, 0], "reports": {"gpt": ["brake"]}}),
            ),
            422,
            "unknown_reporter",
        ),
        (
            "unknown label",
            post_json(
                &srv,
                "/v1/fuse",
                &json!({"context": [1, 0, 0, 0], "reports": {"vlaad": ["fly"]}}),
            ),
            422,
            "unknown_label",
        ),
        (
            "empty coalition",
            post_json(
                &srv,
                "/v1/fuse",
                &json!({"context": [1, 0, 0, 0], "reports": {}}),
            ),
            422,
            "empty_coalition",
        ),
        (
            "truth on fuse",
            post_json(
                &srv,
                "/v1/fuse",
                &json!({"context": [1, 0, 0, 0], "reports": {"vlaad": []}, "truth": ["brake"]}),
            ),
            422,
            "truth_not_accepted",
        ),
        (
            "one bad round in a batch",
            post_json(
                &srv,
                "/v1/fuse",
                &json!({"rounds": [round(&[1.0, 0.0, 0.0, 0.0]), {"context": [1, 0, 0, 0], "reports": {"vlaad": ["fly"]}}]}),
            ),
            422,
            "unknown_label",
        ),
        (
            "batch of mixed dimensions",
            post_json(
                &srv,
                "/v1/fuse",
                &json!({"rounds": [round(&[1.0, 0.0, 0.0, 0.0]), round(&[1.0, 0.0])]}),
            ),
            422,
            "dimension_mismatch",
        ),
        (
            "batch over the limit",
            post_json(
                &srv,
                "/v1/fuse",
                &json!({"rounds": vec![round(&[1.0, 0.0, 0.0, 0.0]); 5]}),
            ),
            422,
            "invalid_request",
        ),
        (
            "empty batch",
            post_json(&srv, "/v1/fuse", &json!({"rounds": []})),
            422,
            "invalid_request",
        ),
        (
            "wrong content type",
            authed(&srv, "POST", "/v1/fuse", b"{}", "text/plain"),
            415,
            "unsupported_media_type",
        ),
        (
            "body too large",
            post_json(&srv, "/v1/fuse", &round(&vec![0.5; 2000])),
            413,
            "payload_too_large",
        ),
        (
            "no token",
            request(
                &srv.addr,
                "POST",
                "/v1/fuse",
                &[("content-type", "application/json")],
                Some(
                    serde_json::to_vec(&round(&[1.0, 0.0, 0.0, 0.0]))
                        .unwrap()
                        .as_slice(),
                ),
            )
            .unwrap(),
            401,
            "unauthorized",
        ),
        (
            "wrong token",
            request(
                &srv.addr,
                "POST",
                "/v1/feedback",
                &[
                    ("content-type", "application/json"),
                    ("authorization", "Bearer nope"),
                ],
                Some(br#"{"round_id": "r-00000001", "labels": []}"#),
            )
            .unwrap(),
            401,
            "unauthorized",
        ),
        (
            "unknown round",
            post_json(
                &srv,
                "/v1/feedback",
                &json!({"round_id": "r-00000099", "labels": []}),
            ),
            404,
            "unknown_round",
        ),
        (
            "non-canonical round id",
            post_json(
                &srv,
                "/v1/feedback",
                &json!({"round_id": "r-1", "labels": []}),
            ),
            404,
            "unknown_round",
        ),
        (
            "feedback unknown label",
            post_json(
                &srv,
                "/v1/feedback",
                &json!({"round_id": id1, "labels": ["fly"]}),
            ),
            422,
            "unknown_label",
        ),
        (
            "feedback extra field",
            post_json(
                &srv,
                "/v1/feedback",
                &json!({"round_id": id1, "labels": [], "truth": []}),
            ),
            422,
            "invalid_request",
        ),
        (
            "feedback missing labels",
            post_json(&srv, "/v1/feedback", &json!({"round_id": id1})),
            422,
            "invalid_request",
        ),
        (
            "conflicting feedback",
            post_json(
                &srv,
                "/v1/feedback",
                &json!({"round_id": id0, "labels": ["stop"]}),
            ),
            409,
            "conflict",
        ),
        ("unknown route", srv.get("/v2/nothing"), 404, "not_found"),
        (
            "wrong method",
            srv.get("/v1/fuse"),
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
            ),
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
        assert_eq!(snapshot(&srv), before, "{what} changed the state");
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
    );
    assert_eq!(again.status, 200);
    assert_eq!(again.header("x-vlmfuse-repeated"), Some("true"));
    assert_eq!(again.json(), fb0.json());
    // Display names name the same labels.
    let again = post_json(
        &srv,
        "/v1/feedback",
        &json!({"round_id": id0, "labels": ["brake", "brake"]}),
    );
    assert_eq!(again.json(), fb0.json());
    assert_eq!(snapshot(&srv), before);

    // The metrics saw all of it.
    let m = String::from_utf8(srv.get("/metrics").body).unwrap();
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
    assert_eq!(srv.get("/healthz").status, 200);
    assert_eq!(srv.get("/readyz").json()["status"], "ready");
    assert_eq!(
        srv.get("/v1/ontology").json()["labels"]
            .as_array()
            .unwrap()
            .len(),
        14
    );
    let spec = srv.get("/openapi.yaml");
    assert_eq!(spec.status, 200);
    assert!(String::from_utf8(spec.body)
        .unwrap()
        .starts_with("openapi:"));
}

/// With a concurrency limit of 1 and slow fuse requests (the documented test-only delay), a
/// second request is refused with 429 at once; a request over the timeout gets 503; SIGTERM lets
/// the request in flight finish before the process exits cleanly.
#[test]
fn overload_timeout_and_graceful_shutdown() {
    let tmp = tempfile::tempdir().unwrap();
    let mut srv = Server::start(
        tmp.path(),
        &["--concurrency-limit", "1", "--request-timeout-s", "2"],
        &[("VLMFUSE_DEBUG_FUSE_DELAY_MS", "1000")],
    );
    let addr = srv.addr.clone();
    let body = serde_json::to_vec(&round(&[1.0, 0.0, 0.5, 0.2])).unwrap();
    let before = srv.state();
    let slow = {
        let (addr, body) = (addr.clone(), body.clone());
        std::thread::spawn(move || {
            request(
                &addr,
                "POST",
                "/v1/fuse",
                &[("content-type", "application/json")],
                Some(&body),
            )
            .unwrap()
        })
    };
    std::thread::sleep(Duration::from_millis(300));
    // Reads are behind the limit too.
    srv.get("/v1/state").expect_error(429, "overloaded");
    let refused = request(
        &addr,
        "POST",
        "/v1/fuse",
        &[("content-type", "application/json")],
        Some(&body),
    )
    .unwrap();
    refused.expect_error(429, "overloaded");
    assert_eq!(refused.header("retry-after"), Some("1"));
    // Probes are not behind the limit.
    assert_eq!(srv.get("/healthz").status, 200);
    assert_eq!(slow.join().unwrap().status, 200);
    // The slow round was stored, the refused one was not.
    assert_eq!(
        srv.state()["rounds"],
        before["rounds"].as_u64().unwrap() + 1
    );
    let m = String::from_utf8(srv.get("/metrics").body).unwrap();
    assert!(m.contains("vlmfuse_overload_total 2"), "{m}");

    // Graceful shutdown: a request in flight when SIGTERM arrives still gets its answer.
    let inflight = {
        let (addr, body) = (addr.clone(), body.clone());
        std::thread::spawn(move || {
            request(
                &addr,
                "POST",
                "/v1/fuse",
                &[("content-type", "application/json")],
                Some(&body),
            )
            .unwrap()
        })
    };
    std::thread::sleep(Duration::from_millis(300));
    srv.sigterm();
    let r = inflight.join().unwrap();
    assert_eq!(r.status, 200, "{:?}", r.json());
    let status = srv.child.wait().unwrap();
    assert!(status.success(), "exit status {status}");
    drop(srv);

    // Timeout: the fuse takes 1 s against a 0.5 s budget; the restarted server kept both rounds.
    let srv = Server::start(
        tmp.path(),
        &["--request-timeout-s", "0.5"],
        &[("VLMFUSE_DEBUG_FUSE_DELAY_MS", "1000")],
    );
    assert_eq!(srv.state()["rounds"], 2);
    let r = request(
        &srv.addr,
        "POST",
        "/v1/fuse",
        &[("content-type", "application/json")],
        Some(&body),
    )
    .unwrap();
    r.expect_error(503, "timeout");
    assert_eq!(
        srv.state()["rounds"],
        2,
        "a timed-out fuse stored its round"
    );
}
