//! The operator page in a real browser (issue 26): headless Chromium (Debian's `chromium`, which
//! scripts/setup-system.sh installs) against the real binary after a few hundred rounds with
//! feedback and two clips through `/v1/infer`. It checks that the page without the token is the
//! login form only, that every panel renders and shows the numbers `/v1/state` gives, that
//! feedback sent from a round's page changes the reputations, and it writes a screenshot of each
//! panel to `VLMFUSE_UI_SCREENSHOTS` (default: the test's target temp dir), the pictures in
//! docs/img come from.

use crate::support::{client, Server};
use headless_chrome::protocol::cdp::Page::CaptureScreenshotFormatOption;
use headless_chrome::{Browser, LaunchOptions, Tab};
use serde_json::{json, Value};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};
use vlmfuse_testkit::clips::h264_clip;
use vlmfuse_testkit::multipart::{content_type, multipart};
use vlmfuse_testkit::server::FakeOpenAi;
use vlmfuse_testkit_models::fixtures::clip_embedder_toml;

const TOKEN: &str = "operator-test-token-7f3a";
const ROUNDS: usize = 300;
/// The dashboard's panels, `#panel-<name>`.
const PANELS: [&str; 6] = [
    "reputations",
    "reliability",
    "calibration",
    "rounds",
    "review",
    "health",
];

fn chromium() -> PathBuf {
    for p in ["/usr/bin/chromium", "/usr/bin/chromium-browser"] {
        if Path::new(p).exists() {
            return PathBuf::from(p);
        }
    }
    panic!("chromium is not installed: scripts/setup-system.sh installs Debian's `chromium`");
}

fn shots_dir() -> PathBuf {
    let dir = std::env::var_os("VLMFUSE_UI_SCREENSHOTS")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("ui-screenshots"));
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

fn authed(srv: &Server, path: &str) -> reqwest::blocking::RequestBuilder {
    client()
        .get(srv.url(path))
        .header("authorization", format!("Bearer {TOKEN}"))
}

fn post_json(srv: &Server, path: &str, body: &Value) -> Value {
    let r = client()
        .post(srv.url(path))
        .header("authorization", format!("Bearer {TOKEN}"))
        .json(body)
        .send()
        .unwrap();
    let status = r.status();
    let v: Value = r.json().unwrap();
    assert!(status.is_success(), "{path}: {status} {v}");
    v
}

/// Evaluates a JavaScript expression in the page and returns its JSON value.
fn js(tab: &Tab, expr: &str) -> Value {
    let r = tab
        .evaluate(&format!("JSON.stringify({expr})"), false)
        .unwrap_or_else(|e| panic!("evaluating {expr}: {e}"));
    let s = r.value.and_then(|v| v.as_str().map(str::to_string));
    s.map(|s| serde_json::from_str(&s).unwrap())
        .unwrap_or(Value::Null)
}

/// Waits until `expr` is truthy in the page.
fn wait_for(tab: &Tab, expr: &str, what: &str) {
    let deadline = Instant::now() + Duration::from_secs(30);
    loop {
        if js(tab, &format!("!!({expr})")) == json!(true) {
            return;
        }
        if Instant::now() > deadline {
            let banner = js(
                tab,
                "document.getElementById('banner')?.textContent ?? null",
            );
            panic!("timed out waiting for {what} ({expr}); banner: {banner}");
        }
        std::thread::sleep(Duration::from_millis(100));
    }
}

fn shot(tab: &Tab, selector: &str, path: &Path) {
    let el = tab
        .find_element(selector)
        .unwrap_or_else(|e| panic!("{selector}: {e}"));
    let png = el
        .capture_screenshot(CaptureScreenshotFormatOption::Png)
        .unwrap_or_else(|e| panic!("screenshot of {selector}: {e}"));
    assert!(
        png.len() > 1000,
        "{selector}: a {} byte screenshot",
        png.len()
    );
    std::fs::write(path, png).unwrap();
}

/// Reports for round `t`: `videollama2` right, `videollava` right on the first labels, and
/// `vlaad` right until round 150, then wrong (the drift the reputation chart shows).
fn round(t: usize, dim: usize, labels: &[String]) -> (Value, Vec<String>) {
    let truth: Vec<String> = labels
        .iter()
        .enumerate()
        .filter(|(k, _)| (t * 7 + k * 3).is_multiple_of(5))
        .map(|(_, l)| l.clone())
        .collect();
    let flipped: Vec<String> = labels
        .iter()
        .filter(|l| !truth.contains(l))
        .take(3)
        .cloned()
        .collect();
    let partial: Vec<String> = truth.iter().take(1).cloned().collect();
    let context: Vec<f64> = (0..dim)
        .map(|i| (((t % 6) * 31 + i * 17) % 23) as f64 / 23.0 + 0.01)
        .collect();
    let vlaad = if t < 150 { truth.clone() } else { flipped };
    (
        json!({"id": format!("fused-{t}"), "context": context,
               "reports": {"videollama2": truth, "videollava": partial, "vlaad": vlaad}}),
        truth,
    )
}

#[test]
#[ignore = "needs chromium (scripts/setup-system.sh installs it; scripts/test runs ignored tests)"]
fn the_operator_page_shows_the_state_and_sends_feedback() {
    let chrome = chromium();
    let tmp = tempfile::tempdir().unwrap();
    let fake = FakeOpenAi::start();
    let mut cfg = format!(
        "reporters = [\"videollama2\", \"videollava\", \"vlaad\"]\n\n[server]\napi_key = \"{TOKEN}\"\n\n\
         [media]\nframes = 4\nmax_bytes = 4000000\n\n[ui]\npoll_ms = 500\ndrift_window = 10\n\n"
    );
    cfg += &clip_embedder_toml(tmp.path());
    cfg += &fake.reporter_toml("videollama2", "frames");
    cfg += &fake.reporter_toml("videollava", "video_url");
    cfg += &fake.labeler_toml();
    let cfg_path = tmp.path().join("ui.toml");
    std::fs::write(&cfg_path, cfg).unwrap();
    let data = tmp.path().join("data");
    let args = ["--config", cfg_path.to_str().unwrap()];
    let srv = Server::start(&data, &args, &[]);

    // Without the token: the data is refused, and the page is the login form.
    let r = client().get(srv.url("/ui/api/summary")).send().unwrap();
    assert_eq!(r.status().as_u16(), 401);

    let dim = authed(&srv, "/v1/state")
        .send()
        .unwrap()
        .json::<Value>()
        .unwrap()["dim"]
        .as_u64()
        .expect("the embedder fixes the dimension") as usize;
    let labels: Vec<String> = authed(&srv, "/v1/ontology")
        .send()
        .unwrap()
        .json::<Value>()
        .unwrap()["labels"]
        .as_array()
        .unwrap()
        .iter()
        .map(|l| l["id"].as_str().unwrap().to_string())
        .collect();

    // A few hundred rounds, each labelled right after it was fused.
    for chunk in (0..ROUNDS).collect::<Vec<_>>().chunks(50) {
        let (rounds, truths): (Vec<Value>, Vec<Vec<String>>) =
            chunk.iter().map(|&t| round(t, dim, &labels)).unzip();
        let out = post_json(&srv, "/v1/fuse", &json!({ "rounds": rounds }));
        for (r, truth) in out["rounds"].as_array().unwrap().iter().zip(truths) {
            post_json(
                &srv,
                "/v1/feedback",
                &json!({"round_id": r["round_id"], "labels": truth}),
            );
        }
    }
    // Two clips, so that rounds have frames and reporter texts.
    let clip = h264_clip(tmp.path(), "dashcam.mp4", "testsrc", 1.0);
    let bytes = std::fs::read(&clip).unwrap();
    let mut infer_round = String::new();
    for _ in 0..2 {
        let r = client()
            .post(srv.url("/v1/infer"))
            .header("authorization", format!("Bearer {TOKEN}"))
            .header("content-type", content_type())
            .body(multipart(&[("video", "dashcam.mp4", &bytes)]))
            .send()
            .unwrap();
        assert_eq!(r.status().as_u16(), 200);
        let v: Value = r.json().unwrap();
        infer_round = v["round_id"].as_str().expect("a round id").to_string();
    }
    let state: Value = authed(&srv, "/v1/state").send().unwrap().json().unwrap();
    assert_eq!(state["labelled_rounds"], json!(ROUNDS));

    let browser = Browser::new(
        LaunchOptions::default_builder()
            .path(Some(chrome))
            .sandbox(false)
            .window_size(Some((1400, 2200)))
            .idle_browser_timeout(Duration::from_secs(120))
            .build()
            .unwrap(),
    )
    .expect("launching chromium");
    let tab: Arc<Tab> = browser.new_tab().unwrap();
    let shots = shots_dir();

    // 1. No cookie: the login form and nothing else.
    tab.navigate_to(&srv.url("/ui")).unwrap();
    tab.wait_until_navigated().unwrap();
    wait_for(&tab, "document.getElementById('login')", "the login form");
    assert_eq!(
        js(&tab, "document.querySelectorAll('section.panel').length"),
        json!(0),
        "the login page shows no panel"
    );
    assert_eq!(
        js(&tab, "document.body.innerText.includes('videollama2')"),
        json!(false),
        "the login page names no reporter"
    );
    shot(&tab, "body", &shots.join("login.png"));

    // A wrong token: still the form, with the error.
    tab.find_element("input[name=token]")
        .unwrap()
        .type_into("not-the-token")
        .unwrap();
    tab.press_key("Enter").unwrap();
    wait_for(
        &tab,
        "location.search.includes('login=failed') && !document.getElementById('login-error').hidden",
        "the wrong-token message",
    );

    // 2. The right token: the page, every panel.
    tab.find_element("input[name=token]")
        .unwrap()
        .type_into(TOKEN)
        .unwrap();
    tab.press_key("Enter").unwrap();
    for panel in PANELS {
        wait_for(
            &tab,
            &format!("document.querySelector('#panel-{panel}[data-ready=\"true\"]')"),
            &format!("panel {panel}"),
        );
    }
    // The cookie is not readable by scripts.
    assert_eq!(
        js(&tab, "document.cookie.includes('vlmfuse_ui')"),
        json!(false)
    );

    // The numbers are /v1/state's.
    let state: Value = authed(&srv, "/v1/state").send().unwrap().json().unwrap();
    for (name, w) in state["reputations"].as_object().unwrap() {
        let shown = js(
            &tab,
            &format!(
                "document.querySelector('td[data-reporter=\"{name}\"][data-field=\"reputation\"]')?.dataset.value ?? null"
            ),
        );
        let shown: f64 = shown.as_str().expect("a reputation cell").parse().unwrap();
        assert_eq!(shown, w.as_f64().unwrap(), "reputation of {name}");
    }
    assert_eq!(
        js(
            &tab,
            "document.getElementById('labelled-rounds').dataset.value"
        ),
        json!(ROUNDS.to_string())
    );
    let n_cells = js(
        &tab,
        "document.querySelectorAll('#panel-reliability [data-reporter][data-label]').length",
    );
    assert!(
        n_cells.as_u64().unwrap() >= (3 * labels.len()) as u64,
        "{n_cells} heat-map cells"
    );
    // vlaad drifted after round 150: its alarm is up.
    let summary: Value = authed(&srv, "/ui/api/summary")
        .send()
        .unwrap()
        .json()
        .unwrap();
    let drift = &summary["drift"]["reporters"][2];
    assert_eq!(drift["reporter"], json!("vlaad"));
    assert!(
        !drift["alarm_at"].as_array().unwrap().is_empty(),
        "vlaad's drift raised an alarm: {drift}"
    );
    assert!(
        js(
            &tab,
            "document.querySelectorAll('#panel-rounds tr[data-round-id]').length"
        )
        .as_u64()
        .unwrap()
            >= 10
    );
    // The review queue lists the rounds nobody labelled (the two clips), in the API's order.
    let review: Value = authed(&srv, "/v1/review?limit=10&window=500")
        .send()
        .unwrap()
        .json()
        .unwrap();
    let want: Vec<Value> = review["queue"]
        .as_array()
        .unwrap()
        .iter()
        .map(|p| p["round_id"].clone())
        .collect();
    assert_eq!(want.len(), 2, "{review}");
    assert_eq!(
        js(
            &tab,
            "[...document.querySelectorAll('#panel-review tr[data-round-id]')].map(r => r.dataset.roundId)"
        ),
        json!(want)
    );
    for panel in PANELS {
        shot(
            &tab,
            &format!("#panel-{panel}"),
            &shots.join(format!("{panel}.png")),
        );
    }
    tab.evaluate("window.scrollTo(0, 0)", false).unwrap();
    let png = tab
        .capture_screenshot(CaptureScreenshotFormatOption::Png, None, None, true)
        .unwrap();
    std::fs::write(shots.join("dashboard.png"), png).unwrap();

    // 3. A round's page: frames, texts, and feedback from its checkboxes.
    tab.evaluate(&format!("location.hash = '#/rounds/{infer_round}'"), false)
        .unwrap();
    wait_for(
        &tab,
        &format!(
            "document.querySelector('#panel-round[data-ready=\"true\"][data-round-id=\"{infer_round}\"]')"
        ),
        "the round's page",
    );
    wait_for(
        &tab,
        "[...document.querySelectorAll('#panel-round img.frame')].some(i => i.complete && i.naturalWidth > 0)",
        "a frame thumbnail",
    );
    let before: Value = authed(&srv, "/v1/state").send().unwrap().json().unwrap();
    // Tick "brake" and "stop", untick everything else.
    tab.evaluate(
        "document.querySelectorAll('#feedback-form input[name=label]').forEach(c => { \
           c.checked = (c.value === 'brake' || c.value === 'stop'); })",
        false,
    )
    .unwrap();
    shot(&tab, "#panel-round", &shots.join("round.png"));
    tab.find_element("#send-feedback").unwrap().click().unwrap();
    wait_for(
        &tab,
        "document.querySelector('#feedback-result[data-status]')",
        "the feedback's answer",
    );
    assert_eq!(
        js(
            &tab,
            "document.getElementById('feedback-result').dataset.status"
        ),
        json!("ok"),
        "{}",
        js(
            &tab,
            "document.getElementById('feedback-result').textContent"
        )
    );
    let after: Value = authed(&srv, "/v1/state").send().unwrap().json().unwrap();
    assert_eq!(after["labelled_rounds"], json!(ROUNDS + 1));
    assert_ne!(
        before["reputations"], after["reputations"],
        "the page's feedback moved the reputations"
    );
    let round: Value = authed(&srv, &format!("/ui/api/rounds/{infer_round}"))
        .send()
        .unwrap()
        .json()
        .unwrap();
    assert_eq!(round["truth"]["brake"], json!(true));
    assert_eq!(round["truth_source"]["brake"], json!("human"));

    // The cookie does not open the writing routes without the page's header.
    let cookie = tab
        .get_cookies()
        .unwrap()
        .into_iter()
        .find(|c| c.name == "vlmfuse_ui")
        .expect("the session cookie");
    assert!(cookie.http_only, "HttpOnly");
    let r = client()
        .post(srv.url("/v1/feedback"))
        .header("cookie", format!("vlmfuse_ui={}", cookie.value))
        .json(&json!({"round_id": infer_round, "labels": []}))
        .send()
        .unwrap();
    assert_eq!(r.status().as_u16(), 401, "the cookie alone does not write");

    // 4. Logging out brings the form back.
    tab.evaluate("location.hash = '#/'", false).unwrap();
    tab.find_element("form[action=\"/ui/logout\"] button")
        .unwrap()
        .click()
        .unwrap();
    wait_for(
        &tab,
        "document.getElementById('login')",
        "the login form again",
    );
    eprintln!("screenshots in {}", shots.display());
}
