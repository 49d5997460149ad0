//! The OpenAI-compatible labeler against a fake chat-completions server on 127.0.0.1:0 that
//! plays back scripted answers, so retries and validation are observable.

use axum::{extract::State, http::StatusCode, routing::post, Json, Router};
use serde_json::{json, Value};
use std::sync::{Arc, Mutex};
use std::time::Duration;
use vlmfuse_labeler::{Label, Labeler, LabelerErrorKind, Ontology, OpenAiConfig, OpenAiLabeler};
use vlmfuse_testkit::server::serve_local;

#[derive(Clone, Default)]
struct Fake {
    /// Scripted replies, consumed in order: (HTTP status, message content).
    replies: Arc<Mutex<Vec<(u16, String)>>>,
    requests: Arc<Mutex<Vec<Value>>>,
}

async fn chat(State(f): State<Fake>, Json(body): Json<Value>) -> (StatusCode, Json<Value>) {
    f.requests.lock().unwrap().push(body);
    let (status, content) = {
        let mut r = f.replies.lock().unwrap();
        if r.is_empty() {
            (500, "no scripted reply left".to_string())
        } else {
            r.remove(0)
        }
    };
    let body = if status == 200 {
        json!({"id": "x", "object": "chat.completion", "choices": [
            {"index": 0, "message": {"role": "assistant", "content": content}, "finish_reason": "stop"}
        ]})
    } else {
        json!({"error": {"message": content}})
    };
    (StatusCode::from_u16(status).unwrap(), Json(body))
}

async fn start(replies: Vec<(u16, &str)>) -> (Fake, String) {
    let fake = Fake {
        replies: Arc::new(Mutex::new(
            replies
                .into_iter()
                .map(|(s, c)| (s, c.to_string()))
                .collect(),
        )),
        ..Default::default()
    };
    let app = Router::new()
        .route("/v1/chat/completions", post(chat))
        .with_state(fake.clone());
    (fake, serve_local(app).await)
}

fn labeler(base_url: String, ontology: Ontology) -> OpenAiLabeler {
    OpenAiLabeler::new(
        ontology,
        OpenAiConfig {
            base_url,
            model: "fake-model".into(),
            timeout: Duration::from_secs(5),
            ..Default::default()
        },
    )
    .unwrap()
}

#[tokio::test]
async fn good_answer_is_accepted_in_one_call() {
    let (fake, url) = start(vec![(
        200,
        r#"{"labels": ["brake", "traffic_light_ahead"]}"#,
    )])
    .await;
    let l = labeler(url, Ontology::default_driving());
    let out = l.label("The light is red, slow down.").await.unwrap();
    assert_eq!(out.labels, vec!["brake", "traffic_light_ahead"]);
    assert_eq!(out.scores.len(), 14);
    assert_eq!(out.score_of("brake"), Some(1.0));
    assert_eq!(out.score_of("stop"), Some(0.0));
    let reqs = fake.requests.lock().unwrap();
    assert_eq!(reqs.len(), 1);
    // The request restricts the model to the ontology and asks for JSON.
    assert_eq!(reqs[0]["response_format"]["type"], "json_object");
    assert_eq!(reqs[0]["model"], "fake-model");
    let system = reqs[0]["messages"][0]["content"].as_str().unwrap();
    assert!(system.contains("adjust_speed_due_to_weather"));
    // The answer goes in verbatim, between the markers of the shared prompt.
    assert_eq!(
        reqs[0]["messages"][1]["content"],
        vlmfuse_labeler::llm::prompt::user_prompt("The light is red, slow down.")
    );
}

#[tokio::test]
async fn one_bad_answer_then_good_is_retried() {
    let (fake, url) = start(vec![
        (200, r#"{"labels": ["brake", "fly_away"]}"#),
        (200, "```json\n{\"labels\": [\"stop\"]}\n```"),
    ])
    .await;
    let l = labeler(url, Ontology::default_driving());
    let out = l.label("Stop at the line.").await.unwrap();
    assert_eq!(out.labels, vec!["stop"]);
    let reqs = fake.requests.lock().unwrap();
    assert_eq!(reqs.len(), 2);
    // The retry tells the model what was wrong.
    let msgs = reqs[1]["messages"].as_array().unwrap();
    assert!(msgs.last().unwrap()["content"]
        .as_str()
        .unwrap()
        .contains("fly_away"));
}

#[tokio::test]
async fn two_bad_answers_fail() {
    let (fake, url) = start(vec![
        (200, "I think brake."),
        (200, r#"{"labels": "brake"}"#),
    ])
    .await;
    let l = labeler(url, Ontology::default_driving());
    let err = l.label("Brake now.").await.unwrap_err();
    assert_eq!(err.kind(), LabelerErrorKind::BadAnswer);
    assert_eq!(fake.requests.lock().unwrap().len(), 2);
}

#[tokio::test]
async fn server_errors_are_retried_then_reported_as_http() {
    let (fake, url) = start(vec![(503, "busy"), (200, r#"{"labels": []}"#)]).await;
    let l = labeler(url.clone(), Ontology::default_driving());
    let out = l.label("Nothing to report.").await.unwrap();
    assert!(out.labels.is_empty());
    assert_eq!(fake.requests.lock().unwrap().len(), 2);

    let (_fake, url) = start(vec![(503, "busy"), (502, "bad gateway")]).await;
    let err = labeler(url, Ontology::default_driving())
        .label("x")
        .await
        .unwrap_err();
    assert_eq!(err.kind(), LabelerErrorKind::Http);

    // A client error is not retried: the request itself is wrong.
    let (fake, url) = start(vec![(401, "no key"), (200, r#"{"labels": []}"#)]).await;
    let err = labeler(url, Ontology::default_driving())
        .label("x")
        .await
        .unwrap_err();
    assert_eq!(err.kind(), LabelerErrorKind::Http);
    assert_eq!(fake.requests.lock().unwrap().len(), 1);
}

#[tokio::test]
async fn custom_ontology_is_enforced() {
    let onto = Ontology::new(vec![
        Label::new("cat", "cat", None),
        Label::new("dog", "dog", Some("a dog is visible")),
    ])
    .unwrap();
    let (_f, url) = start(vec![(200, r#"{"labels": ["dog"]}"#)]).await;
    let out = labeler(url, onto.clone()).label("a dog").await.unwrap();
    assert_eq!(out.labels, vec!["dog"]);
    // A label of the default ontology is unknown here.
    let (_f, url) = start(vec![
        (200, r#"{"labels": ["brake"]}"#),
        (200, r#"{"labels": ["brake"]}"#),
    ])
    .await;
    let err = labeler(url, onto).label("a dog").await.unwrap_err();
    assert_eq!(err.kind(), LabelerErrorKind::BadAnswer);
}

#[tokio::test]
async fn unreachable_server_is_an_http_error() {
    // Bind and drop to get a port that refuses connections.
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let err = labeler(
        format!("http://127.0.0.1:{port}"),
        Ontology::default_driving(),
    )
    .label("x")
    .await
    .unwrap_err();
    assert_eq!(err.kind(), LabelerErrorKind::Http);
}
