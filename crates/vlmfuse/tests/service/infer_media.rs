//! /v1/infer's front half, in-process: uploads decoded and embedded by a tiny random
//! CLIP, stored as rounds whose priors come from the context; every kind of bad media refused
//! with a 4xx while the server keeps serving; no embedder → 503, and /readyz says why.

use crate::support::TestApp;
use serde_json::{json, Value};
use vlmfuse_testkit::clips::{ffmpeg_to, h264_clip};
use vlmfuse_testkit::multipart::multipart;
use vlmfuse_testkit::server::{FakeOpenAi, DRIVING_TEXT, LABELER_LABELS, LABELER_MODEL};
use vlmfuse_testkit_models::fixtures::clip_embedder_toml;

fn config(dir: &std::path::Path, fake: &FakeOpenAi, embedder: bool) -> String {
    let mut c = String::from(
        "reporters = [\"videollama2\", \"videollava\"]\n\n[media]\nframes = 4\n\
         max_bytes = 1000000\nmax_clips = 2\n\n",
    );
    if embedder {
        c += &clip_embedder_toml(dir);
    }
    c += &fake.reporter_toml("videollama2", "frames");
    c += &fake.reporter_toml("videollava", "video_url");
    c += &fake.labeler_toml();
    c
}

#[tokio::test(flavor = "multi_thread")]
async fn clips_are_decoded_embedded_fused_and_stored_and_bad_media_is_refused() {
    let tmp = tempfile::tempdir().unwrap();
    let fake = FakeOpenAi::start();
    let srv = TestApp::from_toml(tmp.path(), &config(tmp.path(), &fake, true)).await;
    let ready = srv.get("/readyz").await;
    assert_eq!(ready.status, 200, "{}", ready.json());
    assert_eq!(ready.json()["infer"]["ready"], true, "{}", ready.json());

    let a = h264_clip(tmp.path(), "a.mp4", "testsrc", 2.0);
    let b = h264_clip(tmp.path(), "b.mp4", "mandelbrot", 2.0);

    // One clip: the round is fused, stored, and carries the clip's metadata.
    let r = srv.post_clip(&a).await;
    let v = r.json();
    assert_eq!(r.status, 200, "{v}");
    assert!(v["round_id"].as_str().unwrap().starts_with("r-"), "{v}");
    assert_eq!(v["coalition"], json!(["videollama2", "videollava"]), "{v}");
    assert_eq!(v["failed"], json!({}));
    assert_eq!(v["posteriors"].as_object().unwrap().len(), 14);
    assert_eq!(v["clip"]["codec"], "h264");
    assert_eq!(v["clip"]["width"], 160);
    let ts = v["clip"]["timestamps_s"].as_array().unwrap();
    assert_eq!(ts.len(), 4, "{v}");
    assert!(ts.windows(2).all(|w| w[0].as_f64() < w[1].as_f64()), "{v}");
    for stage in ["upload", "decode", "embed", "reporters", "label", "fuse"] {
        assert!(v["timings_ms"][stage].as_f64().is_some(), "{stage}: {v}");
    }
    for name in ["videollama2", "videollava"] {
        let rep = &v["reporters"][name];
        assert_eq!(rep["text"], DRIVING_TEXT);
        assert_eq!(rep["labels"], json!(LABELER_LABELS));
        assert!(rep["latency_ms"].as_f64().unwrap() >= 0.0);
        assert_eq!(rep["labeler"], format!("openai:{LABELER_MODEL}"));
    }
    let state = srv.state().await;
    assert_eq!(state["rounds"], 1);
    assert_eq!(
        state["dim"], 16,
        "the context is the tiny CLIP's projection: {state}"
    );

    // The context drives the prior: label round 1, then the same clip again has it as its
    // nearest neighbour (cos 1), so the labelled labels' priors rise above the others'.
    let fb = srv
        .post(
            "/v1/feedback",
            &json!({"round_id": v["round_id"], "labels": ["brake"]}),
        )
        .await;
    assert_eq!(fb.status, 200, "{}", fb.json());
    let again = srv.post_clip(&a).await.json();
    let prior = |v: &Value, l: &str| v["explanation"][l]["prior"].as_f64().unwrap();
    assert!(
        prior(&again, "brake") > prior(&again, "turn_left") + 0.1,
        "{}",
        again["explanation"]
    );
    // A different clip has a different context.
    let two = srv
        .post_multipart(multipart(&[
            ("video", "a.mp4", &std::fs::read(&a).unwrap()),
            ("video", "b.mp4", &std::fs::read(&b).unwrap()),
        ]))
        .await;
    assert_eq!(two.status, 200, "{}", two.json());
    let clips = two.json()["clips"].as_array().unwrap().clone();
    assert_eq!(clips.len(), 2);
    assert_ne!(
        prior(&clips[0], "brake"),
        prior(&clips[1], "brake"),
        "different clips, different contexts"
    );
    let rounds_before = srv.state().await["rounds"].clone();
    assert_eq!(rounds_before, 4);

    // Bad media: each a 4xx with the media error's kind; nothing stored; server still up.
    let wav = ffmpeg_to(
        &["-f", "lavfi", "-i", "sine=frequency=440:duration=1"],
        &tmp.path().join("tone.wav"),
    );
    let big = vec![0u8; 1_500_000];
    // Playlists naming a clip on the server's disk: refused, nothing read (issue 10).
    let hls = format!(
        "#EXTM3U\n#EXT-X-TARGETDURATION:2\n#EXTINF:2,\nfile:{}\n#EXT-X-ENDLIST\n",
        b.display()
    );
    let concat = format!("ffconcat version 1.0\nfile '{}'\n", b.display());
    let cases: Vec<(&str, Vec<u8>, u16, &str)> = vec![
        (
            "hls playlist",
            multipart(&[("video", "list.m3u8", hls.as_bytes())]),
            415,
            "unsupported_container",
        ),
        (
            "ffconcat",
            multipart(&[("video", "list.ffconcat", concat.as_bytes())]),
            415,
            "unsupported_container",
        ),
        (
            "zero bytes",
            multipart(&[("video", "e.mp4", b"")]),
            400,
            "empty",
        ),
        (
            "not a video",
            multipart(&[(
                "video",
                "x.mp4",
                b"hello, this is not a video at all".as_slice(),
            )]),
            415,
            "not_video",
        ),
        (
            "audio only",
            multipart(&[("video", "tone.wav", &std::fs::read(&wav).unwrap())]),
            422,
            "no_video_stream",
        ),
        (
            "truncated",
            multipart(&[("video", "t.mp4", &std::fs::read(&b).unwrap()[..3000])]),
            0,
            "",
        ),
        (
            "over size",
            multipart(&[("video", "big.mp4", &big)]),
            413,
            "too_large",
        ),
        (
            "wrong part name",
            multipart(&[("clip", "a.mp4", b"x".as_slice())]),
            422,
            "invalid_request",
        ),
        ("no parts", multipart(&[]), 422, "invalid_request"),
        (
            "too many clips",
            multipart(&[
                ("video", "1.mp4", b"1"),
                ("video", "2.mp4", b"2"),
                ("video", "3.mp4", b"3"),
            ]),
            422,
            "too_many_clips",
        ),
    ];
    for (what, body, status, kind) in cases {
        let r = srv.post_multipart(body).await;
        let v = r.json();
        if status == 0 {
            assert!((400..500).contains(&r.status), "{what}: {} {v}", r.status);
        } else {
            assert_eq!(r.status, status, "{what}: {v}");
            assert_eq!(v["kind"], kind, "{what}: {v}");
        }
        assert!(
            v["error"].as_str().is_some_and(|e| !e.is_empty()),
            "{what}: {v}"
        );
        assert_eq!(srv.get("/healthz").await.status, 200, "{what}: server down");
    }
    // Not multipart at all.
    let r = srv.post("/v1/infer", &json!({"video": "a.mp4"})).await;
    assert!((400..500).contains(&r.status), "{}", r.json());
    assert_eq!(
        srv.state().await["rounds"],
        rounds_before,
        "bad media stored nothing"
    );

    let metrics = String::from_utf8_lossy(&srv.get("/metrics").await.body).to_string();
    for stage in ["upload", "decode", "embed", "reporters", "label", "fuse"] {
        assert!(
            metrics.contains(&format!("vlmfuse_stage_seconds_count{{stage=\"{stage}\"}}")),
            "no {stage} histogram in /metrics"
        );
    }
}

#[tokio::test(flavor = "multi_thread")]
async fn without_an_embedder_infer_is_unavailable_and_readyz_says_why() {
    let tmp = tempfile::tempdir().unwrap();
    let fake = FakeOpenAi::start();
    let srv = TestApp::from_toml(tmp.path(), &config(tmp.path(), &fake, false)).await;
    let clip = h264_clip(tmp.path(), "a.mp4", "testsrc", 1.0);
    let r = srv.post_clip(&clip).await;
    let v = r.json();
    assert_eq!(r.status, 503, "{v}");
    assert_eq!(v["kind"], "not_ready");
    assert!(v["error"].as_str().unwrap().contains("embedder"), "{v}");
    assert!(
        v["not_ready"]
            .as_array()
            .unwrap()
            .iter()
            .any(|s| s.as_str().unwrap().starts_with("embedder")),
        "{v}"
    );
    let ready = srv.get("/readyz").await.json();
    assert_eq!(ready["infer"]["ready"], false, "{ready}");
    assert!(ready["infer"]["not_ready"]
        .to_string()
        .contains("embedder: not configured"));
    assert_eq!(
        fake.calls("videollama2-7b"),
        0,
        "no reporter ran without a context"
    );
    assert_eq!(srv.state().await["rounds"], 0);
}

/// Uploads a `kill -9` left in the spool are removed at the next start; nothing else there is.
#[tokio::test(flavor = "multi_thread")]
async fn uploads_left_by_a_killed_run_are_removed_at_startup() {
    let tmp = tempfile::tempdir().unwrap();
    let spool = tmp.path().join("data").join("spool");
    std::fs::create_dir_all(&spool).unwrap();
    std::fs::write(spool.join("vlmfuse-clip-abc123.mp4"), b"half an upload").unwrap();
    std::fs::write(spool.join("notes.txt"), b"not ours").unwrap();
    // Another instance sharing the spool (a process that runs) and one that was killed.
    let mut alive = std::process::Command::new("sleep")
        .arg("30")
        .spawn()
        .unwrap();
    let mut dead = std::process::Command::new("true").spawn().unwrap();
    dead.wait().unwrap();
    let theirs = format!("vlmfuse-clip-{}-inflight.mp4", alive.id());
    let killed = format!("vlmfuse-clip-{}-left.mp4", dead.id());
    std::fs::write(spool.join(&theirs), b"an upload in flight").unwrap();
    std::fs::write(spool.join(&killed), b"half an upload").unwrap();
    let _srv = TestApp::from_toml(tmp.path(), "reporters = [\"a\"]\n").await;
    assert!(!spool.join("vlmfuse-clip-abc123.mp4").exists());
    assert!(spool.join("notes.txt").exists());
    assert!(!spool.join(&killed).exists(), "a dead owner's upload stays");
    assert!(
        spool.join(&theirs).exists(),
        "another running instance's upload was deleted"
    );
    alive.kill().unwrap();
    alive.wait().unwrap();
}
