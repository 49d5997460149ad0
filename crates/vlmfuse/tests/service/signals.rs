//! Vehicle-signal tracks in the service: a `signals` part after its `video` part on
//! `/v1/infer` (labels derived, with `[annotate] feedback = true` sent as partial feedback from
//! `kinematics`), `signals` on `/v1/feedback`, and bad tracks refused with a 4xx that stores
//! nothing.

use crate::support::TestApp;
use serde_json::json;
use vlmfuse_testkit::clips::h264_clip;
use vlmfuse_testkit::multipart::multipart;
use vlmfuse_testkit::server::FakeOpenAi;
use vlmfuse_testkit_models::fixtures::clip_embedder_toml;

/// `secs` of a car braking at 4 m/s² from 8 m/s to a standstill at 2 s, then standing.
fn braking_track(secs: f64) -> String {
    let mut s = String::from("t_s,speed_mps,accel_mps2,yaw_rate_dps\n");
    let n = (secs * 10.0).round() as usize;
    for i in 0..=n {
        let t = i as f64 / 10.0;
        let v = (8.0 - 4.0 * t).max(0.0);
        let a = if t < 2.0 { -4.0 } else { 0.0 };
        s += &format!("{t:.1},{v:.3},{a:.3},0.0\n");
    }
    s
}

fn derived(v: &serde_json::Value, label: &str) -> Option<bool> {
    v["labels"]
        .as_array()?
        .iter()
        .find(|d| d["label"] == label)
        .map(|d| d["value"].as_bool().unwrap())
}

#[tokio::test(flavor = "multi_thread")]
async fn a_clip_with_its_signal_track_labels_itself() {
    let tmp = tempfile::tempdir().unwrap();
    let fake = FakeOpenAi::start();
    let mut cfg = String::from(
        "reporters = [\"videollama2\", \"videollava\"]\n\n[media]\nframes = 4\n\n\
         [annotate]\nfeedback = true\n\n",
    );
    cfg += &clip_embedder_toml(tmp.path());
    cfg += &fake.reporter_toml("videollama2", "frames");
    cfg += &fake.reporter_toml("videollava", "frames");
    cfg += &fake.labeler_toml();
    let srv = TestApp::from_toml(tmp.path(), &cfg).await;
    let clip = std::fs::read(h264_clip(tmp.path(), "a.mp4", "testsrc", 4.0)).unwrap();
    let track = braking_track(4.0);

    let r = srv
        .post_multipart(multipart(&[
            ("video", "a.mp4", &clip),
            ("signals", "a.csv", track.as_bytes()),
        ]))
        .await;
    let v = r.json();
    assert_eq!(r.status, 200, "{v}");
    let d = &v["derived"];
    assert_eq!(derived(d, "brake"), Some(true), "{d}");
    assert_eq!(derived(d, "stop"), Some(true), "{d}");
    assert_eq!(derived(d, "turn_left"), Some(false), "{d}");
    let brake = d["labels"]
        .as_array()
        .unwrap()
        .iter()
        .find(|x| x["label"] == "brake")
        .unwrap();
    assert!(brake["confidence"].as_f64().unwrap() > 0.5, "{brake}");
    assert!(!brake["evidence"].as_array().unwrap().is_empty(), "{brake}");
    // Sent as partial feedback from the vehicle.
    let fb = &v["kinematics_feedback"];
    assert_eq!(fb["source"], "kinematics", "{v}");
    assert_eq!(fb["learned"]["brake"], true, "{fb}");
    assert_eq!(fb["learned"]["stop"], true, "{fb}");
    assert!(fb["unknown"]
        .as_array()
        .unwrap()
        .contains(&json!("traffic_light_ahead")));
    let st = srv.state().await;
    assert_eq!(
        (st["rounds"].as_u64(), st["labelled_rounds"].as_u64()),
        (Some(1), Some(1))
    );

    // A person completes the round later; the vehicle's labels stay.
    let id = v["round_id"].as_str().unwrap();
    let r = srv
        .post(
            "/v1/feedback",
            &json!({"round_id": id, "labels": ["junction_ahead"],
                    "known": ["junction_ahead", "traffic_light_ahead"]}),
        )
        .await;
    assert_eq!(r.status, 200, "{}", r.json());
    assert_eq!(r.json()["known"]["brake"], "kinematics");

    // Bad tracks: 422 with the reason, nothing stored, before any model runs.
    let before = srv.state().await;
    let mut backwards = track.clone();
    backwards.push_str("3.5,0,0,0\n");
    let short = braking_track(1.0);
    let nan = track.replace("0.5,6.000", "0.5,NaN");
    for (what, body, needle) in [
        ("time going back", backwards, "time"),
        ("a track shorter than the clip", short, "cover"),
        ("NaN", nan, "finite"),
        (
            "a speed of 200 m/s",
            track.replace("0.5,6.000", "0.5,200"),
            "range",
        ),
    ] {
        let r = srv
            .post_multipart(multipart(&[
                ("video", "a.mp4", &clip),
                ("signals", "a.csv", body.as_bytes()),
            ]))
            .await;
        let e = r.json();
        assert_eq!(r.status, 422, "{what}: {e}");
        assert_eq!(e["kind"], "bad_signals", "{what}: {e}");
        assert!(e["error"].as_str().unwrap().contains(needle), "{what}: {e}");
        assert_eq!(srv.state().await, before, "{what}");
    }
    let r = srv
        .post_multipart(multipart(&[
            ("signals", "a.csv", track.as_bytes()),
            ("video", "a.mp4", &clip),
        ]))
        .await;
    assert_eq!(r.status, 422, "{}", r.json());
    assert_eq!(srv.state().await, before);
}

#[tokio::test(flavor = "multi_thread")]
async fn feedback_takes_a_signal_track() {
    let tmp = tempfile::tempdir().unwrap();
    let srv = TestApp::start(tmp.path(), vlmfuse::Config::default()).await;
    let r = srv
        .post(
            "/v1/fuse",
            &json!({"context": [1.0, 0.5], "reports": {"vlaad": ["brake"], "videollava": []}}),
        )
        .await;
    let id = r.json()["round_id"].as_str().unwrap().to_string();
    let before = srv.state().await;
    let track = braking_track(4.0);
    for (body, status) in [
        (json!({"round_id": id, "signals": "t_s\n0\n0\n"}), 422),
        (
            json!({"round_id": id, "signals": track, "labels": ["brake"]}),
            422,
        ),
        (json!({"round_id": id}), 422),
    ] {
        let r = srv.post("/v1/feedback", &body).await;
        assert_eq!(r.status, status, "{body}: {}", r.json());
        assert_eq!(srv.state().await, before, "{body}");
    }
    let r = srv
        .post("/v1/feedback", &json!({"round_id": id, "signals": track}))
        .await;
    let v = r.json();
    assert_eq!(r.status, 200, "{v}");
    assert_eq!(v["source"], "kinematics");
    assert_eq!(v["learned"]["brake"], true, "{v}");
    assert_eq!(derived(&v["derived"], "stop"), Some(true), "{v}");
    assert!(v["labels"].as_array().unwrap().contains(&json!("stop")));
}
