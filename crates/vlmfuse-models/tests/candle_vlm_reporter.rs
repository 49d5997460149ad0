//! The `kind = "candle"` reporter end to end on the tiny random fixtures in the real file
//! formats: the architecture chosen from `model_type`, the reporter path computing exactly what
//! the parity-tested models compute (the committed transformers greedy ids and first-token
//! logits), batches equal to single runs, dtypes, loading (local, sharded, HF cache),
//! determinism, timeouts, LoRA, and clear errors.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::atomic::AtomicBool;
use std::sync::Arc;
use std::time::{Duration, Instant};

use base64::Engine as _;
use serde_json::Value;
use vlmfuse_models::models::qwen3_vl::Qwen3VlFamily;
use vlmfuse_models::{
    run_all, run_all_batch, BackendPool, CandleVlmConfig, CandleVlmReporter, ClipInput, ClipMeta,
    Frame, LocalReporter, ModelError, PoolConfig, Reporter, ReporterFailure, RoundReporter,
    WeightSource,
};
use vlmfuse_testkit_models::fixtures::qwen3_vl::parity_frame;
use vlmfuse_testkit_models::fixtures::video_llava::{SyntheticClip, PARITY_CLIPS};
use vlmfuse_testkit_models::fixtures::{write_hf_cache_entry, TinyQwen3Vl, TinyVideoLlava};

const PROMPT: &str = "describe the dashcam clip";
/// The seeds the parity references were made from (scripts/parity/*.py).
const QWEN_SEED: u64 = 7;
const LLAVA_SEED: u64 = 7;
const LLAVA_ADAPTER_SEED: u64 = 21;
const TOL: f32 = 1e-4;

fn parity(file: &str) -> Value {
    let p = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../tests/data/parity")
        .join(file);
    serde_json::from_str(&std::fs::read_to_string(&p).unwrap()).unwrap()
}

fn max_abs_diff(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len());
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max)
}

fn u32s(v: &Value) -> Vec<u32> {
    v.as_array()
        .unwrap()
        .iter()
        .map(|x| x.as_u64().unwrap() as u32)
        .collect()
}

/// The reference ids up to (not including) the first end-of-sequence id: what a reporter that
/// stops at EOS must produce.
fn until_eos(ids: &[u32], eos: &[u32]) -> Vec<u32> {
    ids.iter()
        .copied()
        .take_while(|t| !eos.contains(t))
        .collect()
}

/// The synthetic clip of scripts/parity/qwen3_vl.py (same integer formula), with the times
/// the reference gave each frame.
fn qwen_clip(case: &Value) -> Vec<Frame> {
    let n = case["frames"].as_u64().unwrap() as usize;
    let (w, h) = (
        case["width"].as_u64().unwrap() as usize,
        case["height"].as_u64().unwrap() as usize,
    );
    let k0 = case["k0"].as_u64().unwrap() as usize;
    let fps = case["video_fps"].as_f64().unwrap();
    let idx = u32s(&case["indices"]);
    (0..n)
        .map(|i| {
            let rgb = parity_frame(w, h, k0 + i);
            Frame {
                width: w as u32,
                height: h as u32,
                rgb,
                pts_s: idx[i] as f64 / fps,
            }
        })
        .collect()
}

fn llava_clip(name: &str) -> Vec<Frame> {
    PARITY_CLIPS
        .iter()
        .find(|c: &&SyntheticClip| c.name == name)
        .unwrap()
        .render()
}

fn llava_prompt(key: &str) -> &'static str {
    match key {
        "describe" => "Describe the dashcam clip.",
        "manoeuvre" => "What should the car do? Scene: Manoeuvres: Rationale:",
        other => panic!("unknown prompt {other}"),
    }
}

fn input(frames: Vec<Frame>) -> ClipInput {
    ClipInput {
        path: PathBuf::from("clip.mp4"),
        frames: frames.into(),
        meta: ClipMeta::default(),
    }
}

fn qwen_dir(tmp: &Path) -> PathBuf {
    let d = tmp.join("qwen");
    TinyQwen3Vl::default().write(&d, QWEN_SEED).unwrap();
    d
}

fn llava_dirs(tmp: &Path) -> (PathBuf, PathBuf) {
    let d = tmp.join("llava");
    let shape = TinyVideoLlava::default();
    shape.write(&d, LLAVA_SEED).unwrap();
    let a = tmp.join("llava-adapter");
    shape
        .write_lora_adapter(
            &a,
            4,
            8.0,
            LLAVA_ADAPTER_SEED,
            Some(vlmfuse_models::models::video_llava::transformers5_name),
        )
        .unwrap();
    (d, a)
}

fn config(name: &str, dir: &Path, prompt: &str, max_new: usize) -> CandleVlmConfig {
    CandleVlmConfig {
        max_new_tokens: max_new,
        prompt: prompt.into(),
        ..CandleVlmConfig::new(name, WeightSource::local(dir))
    }
}

#[test]
fn qwen_reporter_computes_the_reference_greedy_ids() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = qwen_dir(tmp.path());
    let cases = parity("qwen3_vl/reference.json");
    let mut checked = 0;
    for case in cases["cases"].as_array().unwrap() {
        if case["frames"].as_u64().unwrap() == 0 {
            continue; // the reporter always sends a clip
        }
        let name = case["name"].as_str().unwrap();
        let prompt = case["prompt"].as_str().unwrap();
        let r = CandleVlmReporter::load(config("q", &dir, prompt, 16)).unwrap();
        assert_eq!(r.family().model_type(), "qwen3_vl");
        let t = r.trace(&qwen_clip(case), &AtomicBool::new(false)).unwrap();
        assert_eq!(t.input_ids, u32s(&case["input_ids"]), "{name}: input ids");
        let d = max_abs_diff(
            &t.first_token_logits,
            &serde_json::from_value::<Vec<f32>>(case["first_logits"].clone()).unwrap(),
        );
        assert!(d <= TOL, "{name}: first-token logits differ by {d}");
        let want = until_eos(&u32s(&case["greedy_ids"]), r.family().eos_ids());
        assert_eq!(t.generation.tokens, want, "{name}: generated ids");
        assert_eq!(t.grid["video_grid_thw"], case["video_grid_thw"], "{name}");
        checked += 1;
    }
    assert!(checked >= 3);
}

#[test]
fn video_llava_reporter_computes_the_reference_greedy_ids() {
    let tmp = tempfile::tempdir().unwrap();
    let (dir, adapter) = llava_dirs(tmp.path());
    let cases = parity("video_llava/cases.json");
    let mut checked = 0;
    for case in cases["cases"].as_array().unwrap() {
        let clips = case["clips"].as_array().unwrap();
        if clips.len() != 1 {
            continue;
        }
        let name = case["name"].as_str().unwrap();
        let prompt = llava_prompt(case["prompts"][0].as_str().unwrap());
        let mut cfg = config("v", &dir, prompt, 16);
        if case["adapter"].as_bool().unwrap() {
            cfg.adapter = Some(WeightSource::local(&adapter));
        }
        let r = CandleVlmReporter::load(cfg).unwrap();
        assert_eq!(r.family().model_type(), "video_llava");
        if case["adapter"].as_bool().unwrap() {
            assert!(!r.family().merged_lora_keys().is_empty());
        }
        let frames = llava_clip(clips[0].as_str().unwrap());
        let t = r.trace(&frames, &AtomicBool::new(false)).unwrap();
        assert_eq!(
            vec![t.input_ids.clone()],
            case["input_ids"]
                .as_array()
                .unwrap()
                .iter()
                .map(u32s)
                .collect::<Vec<_>>(),
            "{name}: input ids"
        );
        let want_logits: Vec<f32> = base64::engine::general_purpose::STANDARD
            .decode(case["logits"].as_str().unwrap())
            .unwrap()
            .chunks_exact(4)
            .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
            .collect();
        let d = max_abs_diff(&t.first_token_logits, &want_logits);
        assert!(d <= TOL, "{name}: first-token logits differ by {d}");
        let want = until_eos(&u32s(&case["greedy"][0]), r.family().eos_ids());
        assert_eq!(t.generation.tokens, want, "{name}: generated ids");
        // The processor's 8 frames, spread over the clip's (12 for portrait12; all 5 of short5).
        assert_eq!(t.grid["frames"], frames.len().min(8), "{name}");
        checked += 1;
    }
    assert!(checked >= 3, "{checked} cases");
}

/// Two clips of different sizes (so different prompt lengths for Qwen, padding for both) in one
/// batch give each clip the ids it gets alone.
#[tokio::test]
async fn a_batch_gives_each_clip_its_ids_alone() {
    let tmp = tempfile::tempdir().unwrap();
    let qcases = parity("qwen3_vl/reference.json");
    let qc = qcases["cases"].as_array().unwrap();
    let q_clips = [qwen_clip(&qc[0]), qwen_clip(&qc[2])];
    let (ldir, _) = llava_dirs(tmp.path());
    let l_clips = [llava_clip("landscape"), llava_clip("short5")];
    for (dir, clips) in [(qwen_dir(tmp.path()), q_clips), (ldir, l_clips)] {
        let r = CandleVlmReporter::load(config("b", &dir, PROMPT, 8)).unwrap();
        let never = AtomicBool::new(false);
        let alone: Vec<Vec<u32>> = clips
            .iter()
            .map(|c| r.generate_blocking(c, &never).unwrap().tokens)
            .collect();
        let refs: Vec<&[Frame]> = clips.iter().map(|c| c.as_slice()).collect();
        let batch = r.generate_batch_blocking(&refs, &never).unwrap();
        assert_eq!(batch.len(), 2);
        for (i, g) in batch.iter().enumerate() {
            assert_eq!(g.tokens, alone[i], "{}: clip {i}", r.family().model_type());
        }
        assert!(!alone[0].is_empty());

        // Through the pool and run_all_batch, as /v1/infer calls it.
        let inputs: Vec<ClipInput> = clips.iter().cloned().map(input).collect();
        let texts: Vec<String> = clips
            .iter()
            .map(|c| r.generate(&input(c.clone()), &never).unwrap().text)
            .collect();
        let pool: Arc<dyn Reporter> =
            Arc::new(BackendPool::new("b", Arc::new(r), PoolConfig::default()).unwrap());
        let per_clip = run_all_batch(
            &[RoundReporter::new(pool, Duration::from_secs(60))],
            &inputs,
        )
        .await;
        assert_eq!(per_clip.len(), 2);
        for (i, outs) in per_clip.iter().enumerate() {
            assert_eq!(outs[0].1.as_ref().unwrap().text, texts[i]);
        }
    }
}

/// A clip the processor refuses fails alone; the other clip of the batch still gets its answer.
#[test]
fn a_bad_clip_does_not_sink_the_batch() {
    let tmp = tempfile::tempdir().unwrap();
    let r = CandleVlmReporter::load(config("b", &qwen_dir(tmp.path()), PROMPT, 4)).unwrap();
    let qc = parity("qwen3_vl/reference.json");
    let good = input(qwen_clip(&qc["cases"][0]));
    let bad = input(vec![Frame {
        width: 4,
        height: 4,
        rgb: vec![0; 5],
        pts_s: 0.0,
    }]);
    let never = AtomicBool::new(false);
    let outs = r.generate_batch(&[good.clone(), bad], &never);
    assert_eq!(
        outs[0].as_ref().unwrap().text,
        r.generate(&good, &never).unwrap().text
    );
    assert_eq!(outs[1].as_ref().unwrap_err().kind(), "invalid_input");
}

/// Half precision on the CPU: the tiny models' greedy ids over 8 new tokens equal f32's, and
/// the first-token logits (range ~14) stay within 0.25 of f32's in bf16 (8 mantissa bits;
/// measured 0.05 Qwen3-VL, 0.09 VideoLLaVA) and 0.05 in f16 (measured 0.007, 0.010).
#[test]
fn half_precision_matches_f32_greedy_ids() {
    let tmp = tempfile::tempdir().unwrap();
    let qc = parity("qwen3_vl/reference.json");
    let (ldir, _) = llava_dirs(tmp.path());
    let runs = [
        (qwen_dir(tmp.path()), qwen_clip(&qc["cases"][2])),
        (ldir, llava_clip("landscape")),
    ];
    for (dir, clip) in runs {
        let never = AtomicBool::new(false);
        let f32r = CandleVlmReporter::load(config("f", &dir, PROMPT, 8)).unwrap();
        let want = f32r.trace(&clip, &never).unwrap();
        for dtype in ["bf16", "f16"] {
            let r = CandleVlmReporter::load(CandleVlmConfig {
                dtype: Some(dtype.into()),
                ..config("h", &dir, PROMPT, 8)
            })
            .unwrap();
            let got = r.trace(&clip, &never).unwrap();
            let d = max_abs_diff(&got.first_token_logits, &want.first_token_logits);
            eprintln!(
                "{} {dtype}: max |Δ first logits| vs f32 {d:.4}",
                r.family().model_type()
            );
            let tol = if dtype == "bf16" { 0.25 } else { 0.05 };
            assert!(d < tol, "{} {dtype}: {d}", r.family().model_type());
            assert_eq!(
                got.generation.tokens,
                want.generation.tokens,
                "{} {dtype}",
                r.family().model_type()
            );
        }
    }
}

#[test]
fn unknown_model_type_and_devices_are_clear_errors() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = qwen_dir(tmp.path());
    let mut cfg: Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("config.json")).unwrap()).unwrap();
    cfg["model_type"] = "llava_next_video".into();
    std::fs::write(dir.join("config.json"), cfg.to_string()).unwrap();
    let e = match CandleVlmReporter::load(config("x", &dir, PROMPT, 4)) {
        Err(e) => e,
        Ok(_) => panic!("loaded an unsupported model_type"),
    };
    let msg = e.to_string();
    assert!(matches!(e, ModelError::BadConfig(_)), "{e}");
    for want in ["llava_next_video", "qwen3_vl", "video_llava", "config.json"] {
        assert!(msg.contains(want), "{msg} lacks {want}");
    }

    let (ldir, _) = llava_dirs(tmp.path());
    let e = CandleVlmReporter::load(CandleVlmConfig {
        frames: Some(4),
        ..config("x", &ldir, PROMPT, 4)
    })
    .err()
    .unwrap()
    .to_string();
    assert!(
        e.contains("Qwen3-VL only") && e.contains("num_frames = 8"),
        "{e}"
    );

    let dir = qwen_dir(&tmp.path().join("ok"));
    let bad_dtype = CandleVlmConfig {
        dtype: Some("f8".into()),
        ..config("x", &dir, PROMPT, 4)
    };
    assert!(CandleVlmReporter::load(bad_dtype)
        .err()
        .unwrap()
        .to_string()
        .contains("f8"));
    #[cfg(not(feature = "cuda"))]
    {
        let gpu = CandleVlmConfig {
            device: "cuda:1".into(),
            ..config("x", &dir, PROMPT, 4)
        };
        let e = CandleVlmReporter::load(gpu).err().unwrap();
        assert_eq!(e.kind(), "device");
        assert!(e.to_string().contains("--features cuda"), "{e}");
    }
}

/// Frames decoded from an H.264 clip that the `ffmpeg` CLI makes (the media layer's job in
/// production). Synthetic frames when the CLI is missing, so the test still covers the model.
fn decoded_frames(dir: &Path) -> Vec<Frame> {
    let (w, h, n) = (40u32, 24u32, 5usize);
    let clip = dir.join("clip.mp4");
    let raw = dir.join("clip.rgb");
    let made = Command::new("ffmpeg")
        .args([
            "-hide_banner",
            "-loglevel",
            "error",
            "-y",
            "-f",
            "lavfi",
            "-i",
        ])
        .arg(format!("testsrc=size={w}x{h}:rate=5:duration=1"))
        .args(["-c:v", "libx264", "-pix_fmt", "yuv420p"])
        .arg(&clip)
        .status()
        .map(|s| s.success())
        .unwrap_or(false)
        && Command::new("ffmpeg")
            .args(["-hide_banner", "-loglevel", "error", "-y", "-i"])
            .arg(&clip)
            .args(["-f", "rawvideo", "-pix_fmt", "rgb24"])
            .arg(&raw)
            .status()
            .map(|s| s.success())
            .unwrap_or(false);
    let frame_len = (w * h * 3) as usize;
    let data: Vec<Vec<u8>> = if made {
        let bytes = std::fs::read(&raw).unwrap();
        assert!(bytes.len() >= frame_len * n);
        bytes
            .chunks_exact(frame_len)
            .take(n)
            .map(<[u8]>::to_vec)
            .collect()
    } else {
        eprintln!("ffmpeg CLI unavailable: using synthetic frames");
        (0..n)
            .map(|k| {
                (0..frame_len)
                    .map(|i| ((i * 13 + k * 41) % 256) as u8)
                    .collect()
            })
            .collect()
    };
    data.into_iter()
        .enumerate()
        .map(|(i, rgb)| Frame {
            width: w,
            height: h,
            rgb,
            pts_s: i as f64 / 5.0,
        })
        .collect()
}

fn pooled(r: CandleVlmReporter) -> Arc<BackendPool<CandleVlmReporter>> {
    let name = r.name().to_string();
    Arc::new(BackendPool::new(name, Arc::new(r), PoolConfig::default()).unwrap())
}

#[tokio::test]
async fn generates_deterministically_from_local_sharded_and_hf_cache() {
    let tmp = tempfile::tempdir().unwrap();
    let tiny = TinyQwen3Vl::default();
    let model_dir = tmp.path().join("model");
    tiny.write(&model_dir, 7).unwrap();
    let clip = input(decoded_frames(tmp.path()));

    let t0 = Instant::now();
    let local = pooled(CandleVlmReporter::load(config("local", &model_dir, PROMPT, 8)).unwrap());
    let load_ms = t0.elapsed().as_secs_f64() * 1e3;
    let a = local.run(&clip).await.unwrap();
    let b = local.run(&clip).await.unwrap();
    assert!(!a.text.is_empty(), "empty report");
    assert_eq!(a.text, b.text, "greedy decoding must be deterministic");
    assert_eq!(a.model, "local");
    assert!(a.latency_ms > 0.0);

    let g = local
        .backend()
        .generate_blocking(&clip.frames, &AtomicBool::new(false))
        .unwrap();
    assert_eq!(g.text, a.text);
    assert!(!g.tokens.is_empty() && g.tokens.len() <= 8);
    assert!(g.visual_tokens > 0 && g.prompt_tokens > g.visual_tokens);
    eprintln!(
        "tiny qwen3-vl: load {load_ms:.0} ms, run {:.0} ms, prefill {:.0} ms ({} prompt tokens, \
         {} visual), {} new tokens at {:.1} tok/s: {:?}",
        a.latency_ms,
        g.prefill_ms,
        g.prompt_tokens,
        g.visual_tokens,
        g.tokens.len(),
        g.tokens_per_s(),
        a.text
    );

    let sharded_dir = tmp.path().join("sharded");
    tiny.write_sharded(&sharded_dir, 7).unwrap();
    let sharded =
        pooled(CandleVlmReporter::load(config("sharded", &sharded_dir, PROMPT, 8)).unwrap());
    assert_eq!(sharded.run(&clip).await.unwrap().text, a.text);

    let cache = tmp.path().join("hf");
    let commit = "89abcdef0123456789abcdef0123456789abcdef";
    write_hf_cache_entry(
        &cache,
        "tiny/qwen3-vl",
        "main",
        commit,
        &model_dir,
        &TinyQwen3Vl::FILES,
    )
    .unwrap();
    let hub = WeightSource::hub("tiny/qwen3-vl", "main")
        .with_cache_dir(&cache)
        .offline();
    let cached = pooled(
        CandleVlmReporter::load(CandleVlmConfig {
            max_new_tokens: 8,
            prompt: PROMPT.into(),
            ..CandleVlmConfig::new("hub", hub)
        })
        .unwrap(),
    );
    assert_eq!(cached.run(&clip).await.unwrap().text, a.text);
}

#[tokio::test]
async fn timeout_leaves_the_model_usable() {
    let tmp = tempfile::tempdir().unwrap();
    let (ldir, _) = llava_dirs(tmp.path());
    for dir in [qwen_dir(tmp.path()), ldir] {
        let clip = input(decoded_frames(tmp.path()));
        let pool = pooled(CandleVlmReporter::load(config("slow", &dir, PROMPT, 10_000)).unwrap());
        let r: Arc<dyn Reporter> = pool.clone();
        let t0 = Instant::now();
        let out = run_all(&[RoundReporter::new(r, Duration::from_millis(1))], &clip).await;
        assert!(matches!(out[0].1, Err(ReporterFailure::TimedOut(_))));
        assert!(t0.elapsed() < Duration::from_secs(2));
        // The cancelled generation stops at its next token and frees the model's one worker.
        let freed = tokio::time::timeout(
            Duration::from_secs(10),
            pool.call(|r, _| r.family().eos_ids().to_vec()),
        )
        .await;
        assert!(freed.is_ok(), "model still busy after the timeout");
    }
}

#[test]
fn bad_inputs_are_errors_not_panics() {
    let tmp = tempfile::tempdir().unwrap();
    let tiny = TinyQwen3Vl::default();
    let model_dir = qwen_dir(tmp.path());
    let r = CandleVlmReporter::load(config("x", &model_dir, PROMPT, 4)).unwrap();
    let never = AtomicBool::new(false);
    assert_eq!(
        r.generate_blocking(&[], &never).unwrap_err().kind(),
        "invalid_input"
    );
    let bad = Frame {
        width: 4,
        height: 4,
        rgb: vec![0; 5],
        pts_s: 0.0,
    };
    assert_eq!(
        r.generate_blocking(&[bad], &never).unwrap_err().kind(),
        "invalid_input"
    );

    // A checkpoint missing a tensor fails at load, naming it.
    let broken = tmp.path().join("broken");
    tiny.write(&broken, 7).unwrap();
    let mut t =
        candle_core::safetensors::load(broken.join("model.safetensors"), &candle_core::Device::Cpu)
            .unwrap();
    t.remove("model.language_model.layers.1.mlp.up_proj.weight");
    candle_core::safetensors::save(&t, broken.join("model.safetensors")).unwrap();
    let e = match CandleVlmReporter::load(config("b", &broken, PROMPT, 4)) {
        Err(e) => e,
        Ok(_) => panic!("loaded a model with a missing tensor"),
    };
    assert!(matches!(e, ModelError::BadWeights { .. }), "{e}");
    assert!(e.to_string().contains("up_proj"), "{e}");

    let empty = tmp.path().join("empty");
    std::fs::create_dir_all(&empty).unwrap();
    let e = match CandleVlmReporter::load(config("m", &empty, PROMPT, 4)) {
        Err(e) => e,
        Ok(_) => panic!("loaded from an empty dir"),
    };
    assert_eq!(e.kind(), "missing_weights");
}

/// The adapter reaches the reporter: the modules it names are merged (Qwen3-VL here; the
/// VideoLLaVA adapter is checked against transformers + PEFT in the reference-ids test).
#[test]
fn lora_adapter_changes_the_reporters_logits() {
    let tmp = tempfile::tempdir().unwrap();
    let tiny = TinyQwen3Vl::default();
    let dir = qwen_dir(tmp.path());
    let adir = tmp.path().join("adapter");
    tiny.write_lora_adapter(&adir, 2, 8.0, 99).unwrap();
    let clip = qwen_clip(&parity("qwen3_vl/reference.json")["cases"][0]);
    let never = AtomicBool::new(false);
    let base = CandleVlmReporter::load(config("base", &dir, PROMPT, 2)).unwrap();
    let tuned = CandleVlmReporter::load(CandleVlmConfig {
        adapter: Some(WeightSource::local(&adir)),
        ..config("tuned", &dir, PROMPT, 2)
    })
    .unwrap();
    assert!(base.family().merged_lora_keys().is_empty());
    assert_eq!(tuned.family().merged_lora_keys().len(), 2 * tiny.layers);
    let d = max_abs_diff(
        &base.trace(&clip, &never).unwrap().first_token_logits,
        &tuned.trace(&clip, &never).unwrap().first_token_logits,
    );
    assert!(d > 1e-3, "adapter did not change the logits ({d})");
    assert!(tuned
        .family()
        .as_any()
        .downcast_ref::<Qwen3VlFamily>()
        .is_some());
}

/// Sampling is kept: with a temperature, a seed reproduces its answer, another seed changes it
/// (on this random model), and a clip's sampled answer does not depend on its batch.
#[test]
fn sampling_is_seeded_per_clip() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = qwen_dir(tmp.path());
    let qc = parity("qwen3_vl/reference.json");
    let clips = [qwen_clip(&qc["cases"][0]), qwen_clip(&qc["cases"][2])];
    let never = AtomicBool::new(false);
    let sampled = |seed: u64| {
        CandleVlmReporter::load(CandleVlmConfig {
            temperature: Some(1.5),
            top_p: Some(0.95),
            seed,
            ..config("s", &dir, PROMPT, 12)
        })
        .unwrap()
    };
    let a = sampled(1);
    let a1 = a.generate_blocking(&clips[1], &never).unwrap().tokens;
    assert_eq!(a1, a.generate_blocking(&clips[1], &never).unwrap().tokens);
    let seeds_differ = (2..8).any(|s| {
        sampled(s)
            .generate_blocking(&clips[1], &never)
            .unwrap()
            .tokens
            != a1
    });
    assert!(seeds_differ, "no seed changed the sampled answer");
    let greedy = CandleVlmReporter::load(config("g", &dir, PROMPT, 12)).unwrap();
    assert_ne!(
        greedy.generate_blocking(&clips[1], &never).unwrap().tokens,
        a1,
        "temperature 1.5 gave the greedy answer"
    );
    let refs: Vec<&[Frame]> = clips.iter().map(|c| c.as_slice()).collect();
    let batch = a.generate_batch_blocking(&refs, &never).unwrap();
    assert_eq!(batch[1].tokens, a1);
}

/// Without `frames`, Qwen3-VL takes the frames its checkpoint's video processor samples, as
/// transformers does: the tiny fixture asks for 2 fps between 2 and 8 frames, so of a 10 s clip
/// at 10 fps (100 frames) it takes `np.linspace(0, 99, 8).round()` = 0, 14, 28, 42, 57, 71, 85,
/// 99 (the media layer's uniform sample would be frames 7, 19, ..., 94). The frames given to a
/// reporter under its name in `own_frames` are the ones it runs on; with `frames` set, the
/// media layer's frames are spread as before.
#[test]
fn qwen_takes_the_frames_its_checkpoint_samples() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = qwen_dir(tmp.path());
    let clip = vlmfuse_testkit::clips::h264_clip(tmp.path(), "c.mp4", "testsrc", 10.0);
    let limits = vlmfuse_media::MediaLimits::default();
    let info = vlmfuse_media::probe(&clip, &limits).unwrap();
    let r = CandleVlmReporter::load(config("q", &dir, PROMPT, 3)).unwrap();
    let times = LocalReporter::frame_times(&r, info.duration_s, info.fps).expect("own sampler");
    let own = vlmfuse_media::sample_frames_at(
        &clip,
        &times,
        vlmfuse_media::FrameSize::Native,
        &limits,
        &vlmfuse_media::Interrupt::new(),
    )
    .unwrap();
    // Frame numbers from the presentation times (the clip's rate is constant).
    let numbers = |c: &vlmfuse_media::DecodedClip| -> Vec<usize> {
        c.frames
            .iter()
            .map(|f| (f.pts_s * info.fps).round() as usize)
            .collect()
    };
    let idx = numbers(&own);
    assert_eq!(idx, vec![0, 14, 28, 42, 57, 71, 85, 99], "{times:?}");
    // The media layer's uniform sample of 8 frames: other frames.
    let media =
        vlmfuse_media::sample_frames(&clip, &vlmfuse_media::SampleOptions::default(), &limits)
            .unwrap();
    assert_ne!(numbers(&media), idx);
    // The reporter runs on the frames given under its name.
    let own_frames: Arc<[Frame]> = own.frames.into_iter().map(|f| f.frame).collect();
    let media_frames: Arc<[Frame]> = media.frames.into_iter().map(|f| f.frame).collect();
    let mut input = ClipInput {
        path: clip.clone(),
        frames: media_frames.clone(),
        meta: ClipMeta::default(),
    };
    input.meta.own_frames.insert("q".into(), own_frames.clone());
    let cancel = AtomicBool::new(false);
    let got = r.generate(&input, &cancel).unwrap().text;
    let want = r.trace(&own_frames, &cancel).unwrap().generation.text;
    assert_eq!(got, want);
    assert_eq!(input.frames_for("someone else").len(), media_frames.len());
    // A fixed frame count: no sampler of its own.
    let fixed = CandleVlmReporter::load(CandleVlmConfig {
        frames: Some(4),
        ..config("f", &dir, PROMPT, 3)
    })
    .unwrap();
    assert!(LocalReporter::frame_times(&fixed, info.duration_s, info.fps).is_none());
    // Nothing to sample from a clip of no duration or rate.
    assert!(LocalReporter::frame_times(&r, 0.0, 10.0).is_none());
    assert!(LocalReporter::frame_times(&r, 10.0, f64::NAN).is_none());
}
