//! The operator page's routes in-process (docs/UI.md): who may read what (the login form, the
//! sealed cookie, the page's header on writes), that the panels' numbers are the state's and
//! survive a restart, pagination, a round's page, bad requests, the metrics the page adds, and
//! that none of its reads or refusals change state. The browser test (process tests) drives the
//! same page in Chromium.

use crate::support::{Resp, TestApp};
use serde_json::{json, Value};
use vlmfuse::Config;

const KEY: &str = "page-key-9";

fn round(t: usize) -> Value {
    let truth_b = t.is_multiple_of(3);
    let ctx: Vec<f64> = (0..4).map(|i| ((t * 5 + i * 3) % 7) as f64 + 0.5).collect();
    let good: Vec<&str> = if truth_b { vec!["brake"] } else { vec![] };
    let bad: Vec<&str> = if truth_b { vec![] } else { vec!["stop"] };
    json!({"id": format!("clip-{t}"), "context": ctx,
           "reports": {"vlaad": good, "videollama2": good, "videollava": bad}})
}

fn truth(t: usize) -> Vec<&'static str> {
    if t.is_multiple_of(3) {
        vec!["brake"]
    } else {
        vec![]
    }
}

async fn req(
    srv: &TestApp,
    method: &str,
    path: &str,
    headers: &[(&str, &str)],
    body: &str,
) -> Resp {
    srv.request(method, path, headers, body.as_bytes().to_vec())
        .await
}

async fn bearer_get(srv: &TestApp, path: &str) -> Resp {
    let auth = format!("Bearer {KEY}");
    req(srv, "GET", path, &[("authorization", &auth)], "").await
}

async fn post_authed(srv: &TestApp, path: &str, body: &Value) -> Resp {
    let auth = format!("Bearer {KEY}");
    req(
        srv,
        "POST",
        path,
        &[
            ("authorization", &auth),
            ("content-type", "application/json"),
        ],
        &body.to_string(),
    )
    .await
}

/// `n` rounds, each labelled after it is fused.
async fn fill(srv: &TestApp, n: usize) {
    for t in 0..n {
        let r = post_authed(srv, "/v1/fuse", &round(t)).await;
        assert_eq!(r.status, 200, "{:?}", r.json());
        let id = r.json()["round_id"].as_str().unwrap().to_string();
        let f = post_authed(
            srv,
            "/v1/feedback",
            &json!({"round_id": id, "labels": truth(t)}),
        )
        .await;
        assert_eq!(f.status, 200, "{:?}", f.json());
    }
}

fn keyed() -> Config {
    let mut cfg = Config::default();
    cfg.server.api_key = Some(KEY.into());
    cfg
}

/// The `vlmfuse_ui=...` pair of a Set-Cookie header.
fn cookie_of(r: &Resp) -> String {
    let c = r.header("set-cookie").expect("a cookie");
    c.split(';').next().unwrap().to_string()
}

#[tokio::test(flavor = "multi_thread")]
async fn without_the_token_the_page_is_the_login_form_and_the_data_is_refused() {
    let tmp = tempfile::tempdir().unwrap();
    let srv = TestApp::start(tmp.path(), keyed()).await;
    fill(&srv, 3).await;
    let page = srv.get("/ui").await;
    assert_eq!(page.status, 200);
    let html = String::from_utf8(page.body.clone()).unwrap();
    assert!(html.contains("id=\"login\""), "{html}");
    assert!(
        !html.contains("panel-reputations"),
        "the login page has no panel"
    );
    assert!(page.header("content-security-policy").is_some());
    for path in [
        "/ui/api/summary",
        "/ui/api/rounds",
        "/ui/api/rounds/r-00000000",
        "/ui/api/rounds/r-00000000/frames/0",
    ] {
        srv.get(path).await.expect_error(401, "unauthorized");
    }
    // A forged or expired cookie opens nothing.
    for forged in [
        "vlmfuse_ui=99999999999.00",
        "vlmfuse_ui=1.0000000000000000000000000000000000000000000000000000000000000000",
        "vlmfuse_ui=garbage",
    ] {
        req(&srv, "GET", "/ui/api/summary", &[("cookie", forged)], "")
            .await
            .expect_error(401, "unauthorized");
    }
    // The bearer token opens the data; the assets are open (they hold no data).
    assert_eq!(bearer_get(&srv, "/ui/api/summary").await.status, 200);
    assert_eq!(srv.get("/ui/app.js").await.status, 200);
    assert_eq!(srv.get("/ui/app.css").await.status, 200);
    let root = srv.get("/").await;
    assert_eq!(root.status, 303);
    assert_eq!(root.header("location"), Some("/ui"));
}

#[tokio::test(flavor = "multi_thread")]
async fn the_login_cookie_opens_reads_and_with_the_page_header_writes() {
    let tmp = tempfile::tempdir().unwrap();
    let srv = TestApp::start(tmp.path(), keyed()).await;
    fill(&srv, 2).await;
    // An unlabelled round for the page's feedback.
    assert_eq!(post_authed(&srv, "/v1/fuse", &round(2)).await.status, 200);
    let form = [("content-type", "application/x-www-form-urlencoded")];

    let wrong = req(&srv, "POST", "/ui/login", &form, "token=nope").await;
    assert_eq!(wrong.status, 303);
    assert_eq!(wrong.header("location"), Some("/ui?login=failed"));
    assert!(wrong.header("set-cookie").is_none());

    let ok = req(&srv, "POST", "/ui/login", &form, &format!("token={KEY}")).await;
    assert_eq!(ok.status, 303);
    assert_eq!(ok.header("location"), Some("/ui"));
    let set = ok.header("set-cookie").unwrap().to_string();
    for attr in ["HttpOnly", "SameSite=Strict", "Path=/", "Max-Age="] {
        assert!(set.contains(attr), "{set} lacks {attr}");
    }
    assert!(
        !set.contains(KEY),
        "the cookie does not carry the key: {set}"
    );
    let cookie = cookie_of(&ok);

    let page = req(&srv, "GET", "/ui", &[("cookie", &cookie)], "").await;
    let html = String::from_utf8(page.body).unwrap();
    assert!(html.contains("panel-reputations"), "the page itself");
    let s = req(&srv, "GET", "/ui/api/summary", &[("cookie", &cookie)], "").await;
    assert_eq!(s.status, 200);

    // A write with the cookie alone is refused; with the page's header it goes through.
    let body = json!({"round_id": "r-00000002", "labels": ["stop"]}).to_string();
    let json_ct = ("content-type", "application/json");
    let before = srv.state().await;
    req(
        &srv,
        "POST",
        "/v1/feedback",
        &[("cookie", &cookie), json_ct],
        &body,
    )
    .await
    .expect_error(401, "unauthorized");
    assert_eq!(srv.state().await, before, "a refused write changes nothing");
    let w = req(
        &srv,
        "POST",
        "/v1/feedback",
        &[("cookie", &cookie), ("x-vlmfuse-ui", "1"), json_ct],
        &body,
    )
    .await;
    assert_eq!(w.status, 200, "{:?}", w.json());
    assert_ne!(srv.state().await["reputations"], before["reputations"]);

    // Logging out clears it.
    let out = req(&srv, "POST", "/ui/logout", &[("cookie", &cookie)], "").await;
    assert_eq!(out.status, 303);
    assert!(out.header("set-cookie").unwrap().contains("Max-Age=0"));

    // A form without the token is a clear 4xx, never a 500.
    let bad = req(&srv, "POST", "/ui/login", &form, "user=x").await;
    assert_eq!(bad.status, 422, "{}", String::from_utf8_lossy(&bad.body));
}

#[tokio::test(flavor = "multi_thread")]
async fn the_panels_hold_the_states_numbers_and_survive_a_restart() {
    let tmp = tempfile::tempdir().unwrap();
    let summary_before;
    let rounds_before;
    {
        let srv = TestApp::start(tmp.path(), keyed()).await;
        fill(&srv, 40).await;
        let s = bearer_get(&srv, "/ui/api/summary").await.json();
        let state = srv.state().await;
        assert_eq!(s["state"], state, "the summary carries /v1/state as it is");
        let pts = s["reputation_history"]["points"].as_array().unwrap();
        assert_eq!(pts.len(), 40);
        assert_eq!(pts.last().unwrap()["labelled"], json!(40));
        let last_w: Vec<f64> = pts.last().unwrap()["w"]
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v.as_f64().unwrap())
            .collect();
        let state_w: Vec<f64> = s["reporters"]
            .as_array()
            .unwrap()
            .iter()
            .map(|r| state["reputations"][r.as_str().unwrap()].as_f64().unwrap())
            .collect();
        assert_eq!(
            last_w, state_w,
            "the chart ends at the reputations in force"
        );
        // vlaad and videollama2 say "brake" exactly when it is true; videollava says "stop"
        // whenever brake is false, and stop is never true.
        let order: Vec<&str> = s["reporters"]
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v.as_str().unwrap())
            .collect();
        let labels: Vec<&str> = s["labels"]
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v["id"].as_str().unwrap())
            .collect();
        let (brake, stop) = (
            labels.iter().position(|l| *l == "brake").unwrap(),
            labels.iter().position(|l| *l == "stop").unwrap(),
        );
        let rel = &s["reliability"]["overall"];
        let vlaad = order.iter().position(|r| *r == "vlaad").unwrap();
        let llava = order.iter().position(|r| *r == "videollava").unwrap();
        assert_eq!(rel["tpr"][vlaad][brake], json!(1.0));
        assert_eq!(rel["fpr"][vlaad][brake], json!(0.0));
        assert_eq!(rel["tpr"][llava][stop], Value::Null, "stop never true");
        assert_eq!(
            rel["fpr"][llava][stop],
            json!(26.0 / 40.0),
            "stop said on the 26 rounds without brake"
        );
        assert_eq!(rel["positives"][vlaad][brake], json!(14));
        assert_eq!(s["calibration"]["rounds"], json!(40));
        assert_eq!(s["calibration"]["pairs"], json!(40 * labels.len()));
        assert!(s["calibration"]["ece"].as_f64().is_some());
        assert_eq!(
            s["serving"]["decisions"]
                .as_object()
                .unwrap()
                .values()
                .map(|v| v.as_u64().unwrap())
                .sum::<u64>(),
            40
        );
        summary_before = s;
        rounds_before = bearer_get(&srv, "/ui/api/rounds?limit=7").await.json();
    }
    // A restart seeds the panels from the store: the same numbers.
    let srv = TestApp::start(tmp.path(), keyed()).await;
    let s = bearer_get(&srv, "/ui/api/summary").await.json();
    for k in [
        "state",
        "reputation_history",
        "reliability",
        "calibration",
        "drift",
    ] {
        assert_eq!(s[k], summary_before[k], "{k} after a restart");
    }
    assert_eq!(
        s["serving"]["decisions"],
        summary_before["serving"]["decisions"]
    );
    assert_eq!(
        bearer_get(&srv, "/ui/api/rounds?limit=7").await.json(),
        rounds_before
    );
}

#[tokio::test(flavor = "multi_thread")]
async fn rounds_page_newest_first_and_a_round_shows_its_truth() {
    let tmp = tempfile::tempdir().unwrap();
    let srv = TestApp::start(tmp.path(), keyed()).await;
    fill(&srv, 25).await;
    // One more, unlabelled.
    post_authed(&srv, "/v1/fuse", &round(25)).await;
    let mut seen = Vec::new();
    let mut before: Option<u64> = None;
    loop {
        let q = match before {
            Some(b) => format!("/ui/api/rounds?limit=10&before={b}"),
            None => "/ui/api/rounds?limit=10".into(),
        };
        let page = bearer_get(&srv, &q).await.json();
        assert_eq!(page["total"], json!(26));
        for r in page["rounds"].as_array().unwrap() {
            seen.push(r["seq"].as_u64().unwrap());
        }
        match page["next_before"].as_u64() {
            Some(b) => before = Some(b),
            None => break,
        }
    }
    assert_eq!(
        seen,
        (0..26).rev().collect::<Vec<u64>>(),
        "every round once, newest first"
    );

    let first = bearer_get(&srv, "/ui/api/rounds?limit=1").await.json();
    let newest = &first["rounds"][0];
    assert_eq!(newest["labelled"], json!(false));
    assert_eq!(newest["clip"], json!("clip-25"));
    assert_eq!(newest["reporters"]["videollava"], json!(["stop"]));

    let r = bearer_get(&srv, "/ui/api/rounds/r-00000003").await.json();
    assert_eq!(r["truth"]["brake"], json!(true));
    assert_eq!(r["truth"]["stop"], json!(false));
    assert_eq!(r["truth_source"]["brake"], json!("human"));
    assert_eq!(r["feedback"].as_array().unwrap().len(), 1);
    assert_eq!(r["frames"], json!([]), "a /v1/fuse round has no frames");
    let q: f64 = r["posteriors"]["brake"].as_f64().unwrap();
    assert!((0.0..=1.0).contains(&q));
    assert!(r["explanation"]["brake"]["contributions"]["vlaad"].is_number());
    let unlabelled = bearer_get(&srv, "/ui/api/rounds/r-00000025").await.json();
    assert_eq!(unlabelled["truth"]["brake"], Value::Null);

    // Bad requests: clear 4xx, nothing changes.
    let before = srv.state().await;
    bearer_get(&srv, "/ui/api/rounds/r-00000099")
        .await
        .expect_error(404, "unknown_round");
    bearer_get(&srv, "/ui/api/rounds/nonsense")
        .await
        .expect_error(404, "unknown_round");
    bearer_get(&srv, "/ui/api/rounds/r-00000003/frames/0")
        .await
        .expect_error(404, "not_found");
    bearer_get(&srv, "/ui/api/rounds/r-00000003/frames/x")
        .await
        .expect_error(400, "invalid_request");
    bearer_get(&srv, "/ui/api/rounds?limit=0")
        .await
        .expect_error(422, "invalid_request");
    bearer_get(&srv, "/ui/api/rounds?limit=101")
        .await
        .expect_error(422, "invalid_request");
    bearer_get(&srv, "/ui/api/rounds?before=-1")
        .await
        .expect_error(400, "invalid_request");
    bearer_get(&srv, "/ui/api/rounds?page=2")
        .await
        .expect_error(400, "invalid_request");
    assert_eq!(srv.state().await, before);
}

#[tokio::test(flavor = "multi_thread")]
async fn the_page_can_be_turned_off_and_needs_no_login_without_a_key() {
    let tmp = tempfile::tempdir().unwrap();
    let open = TestApp::start(&tmp.path().join("a"), Config::default()).await;
    let html = String::from_utf8(open.get("/ui").await.body).unwrap();
    assert!(
        html.contains("panel-reputations"),
        "no key: the page at once"
    );
    assert_eq!(open.get("/ui/api/summary").await.status, 200);
    assert!(
        html.contains("name=\"vlmfuse-poll-ms\" content=\"2000\""),
        "the poll interval from [ui]"
    );

    let mut cfg = Config::default();
    cfg.ui.enabled = false;
    let off = TestApp::start(&tmp.path().join("b"), cfg).await;
    for p in ["/ui", "/ui/app.js", "/ui/api/summary", "/ui/api/rounds"] {
        assert_eq!(off.get(p).await.status, 404, "{p}");
    }
}

#[tokio::test(flavor = "multi_thread")]
async fn metrics_gain_decisions_and_agreement() {
    let tmp = tempfile::tempdir().unwrap();
    let srv = TestApp::start(tmp.path(), Config::default()).await;
    for t in 0..5 {
        let r = srv.post("/v1/fuse", &round(t)).await;
        assert_eq!(r.status, 200);
    }
    let m = String::from_utf8(srv.get("/metrics").await.body).unwrap();
    let decisions: f64 = m
        .lines()
        .filter(|l| l.starts_with("vlmfuse_decisions_total{"))
        .filter_map(|l| l.rsplit(' ').next()?.parse::<f64>().ok())
        .sum();
    assert_eq!(decisions, 5.0, "{m}");
    let agree = m
        .lines()
        .find(|l| l.starts_with("vlmfuse_reporter_agreement{") && l.contains("reporter=\"vlaad\""))
        .unwrap_or_else(|| panic!("no agreement gauge:\n{m}"));
    let v: f64 = agree.rsplit(' ').next().unwrap().parse().unwrap();
    assert!((0.0..=1.0).contains(&v), "{agree}");
    // Who serves, and the scores that decide it: Dawid-Skene, with no labelled round yet.
    let serving = |p: &str| {
        m.lines()
            .find(|l| {
                l.starts_with("vlmfuse_serving{") && l.contains(&format!("predictor=\"{p}\""))
            })
            .and_then(|l| l.rsplit(' ').next()?.parse::<f64>().ok())
    };
    assert_eq!(serving("dawid_skene"), Some(1.0), "{m}");
    assert_eq!(serving("majority_vote"), Some(0.0), "{m}");
    assert_eq!(serving("model"), Some(0.0), "{m}");
    let st = srv.state().await;
    assert_eq!(st["serving"]["predictor"], json!("dawid_skene"));
    assert_eq!(st["serving"]["rule"], json!("switch"));
    assert_eq!(st["serving"]["scores"][1]["predictor"], json!("model"));
    assert_eq!(st["serving"]["scores"][1]["errors"], json!(0.0));
}

#[tokio::test(flavor = "multi_thread")]
async fn the_state_says_who_serves_and_on_what_scores() {
    let tmp = tempfile::tempdir().unwrap();
    let srv = TestApp::start(tmp.path(), keyed()).await;
    fill(&srv, 30).await;
    let st = srv.state().await;
    let g = st["serving"]["scores"].as_array().unwrap().clone();
    assert_eq!(g.len(), 5, "{g:?}");
    let loss = |p: &str| {
        g.iter()
            .find(|c| c["predictor"] == json!(p))
            .and_then(|c| c["loss"].as_f64())
            .unwrap()
    };
    // The rule of docs/METHOD.md §3: whoever serves has a loss within the margin (3) of the
    // lowest.
    let now = st["serving"]["predictor"].as_str().unwrap().to_string();
    let best = [
        "dawid_skene",
        "model",
        "majority_vote",
        "paper",
        "model_paper_mean",
    ]
    .iter()
    .map(|p| loss(p))
    .fold(f64::INFINITY, f64::min);
    assert!(loss(&now) <= best + 3.0, "{now} serves on {g:?}");
    assert!(
        g.iter()
            .all(|c| (0.0..=1.0).contains(&c["micro_f1"].as_f64().unwrap())),
        "{g:?}"
    );
    // Every response's decision is the same predictor.
    let r = post_authed(&srv, "/v1/fuse", &round(99)).await.json();
    assert_eq!(r["decision"], st["serving"]["predictor"]);
    assert!(r["decided_by"]
        .as_object()
        .unwrap()
        .values()
        .all(|p| *p == st["serving"]["predictor"]));
    assert_eq!(r["decision_score"]["predictor"], st["serving"]["predictor"]);
}

#[tokio::test(flavor = "multi_thread")]
async fn the_panels_work_under_the_paper_method_too() {
    let tmp = tempfile::tempdir().unwrap();
    let mut cfg = keyed();
    cfg.fusion.method = vlmfuse_fusion::Method::Paper;
    let srv = TestApp::start(tmp.path(), cfg).await;
    fill(&srv, 12).await;
    let s = bearer_get(&srv, "/ui/api/summary").await.json();
    assert_eq!(s["state"]["method"], json!("paper"));
    assert_eq!(s["state"], srv.state().await);
    assert_eq!(
        s["reputation_history"]["points"].as_array().unwrap().len(),
        12
    );
    assert_eq!(s["serving"]["decisions"], json!({"model": 12}));
    assert_eq!(s["reliability"]["overall"]["rounds"], json!(12));
    assert!(
        s["reliability"]["recent"]["tpr"][0][0].is_number(),
        "the paper method's own estimates"
    );
    let r = bearer_get(&srv, "/ui/api/rounds/r-00000000").await.json();
    assert_eq!(r["method"], json!("paper"));
    assert_eq!(
        s["state"]["serving"],
        json!({"predictor": "model"}),
        "no gate under paper"
    );
}
