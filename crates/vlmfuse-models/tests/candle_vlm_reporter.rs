//! The in-process Qwen3-VL reporter end to end on a tiny random model in the real file formats:
//! loading (local dir, sharded, HF cache), generation from decoded clip frames, determinism,
//! timeouts, and the LoRA merge on the real key names.

use std::path::Path;
use std::process::Command;
use std::sync::atomic::AtomicBool;
use std::sync::Arc;
use std::time::{Duration, Instant};

use candle_core::{DType, Device, Tensor};
use vlmfuse_models::{
    run_all, BackendPool, CandleVlmConfig, CandleVlmReporter, ClipInput, ClipMeta, Frame,
    LocalReporter, ModelError, PoolConfig, Reporter, ReporterFailure, RoundReporter, WeightSource,
};
use vlmfuse_testkit::fixtures::{write_hf_cache_entry, TinyQwen3Vl};

const PROMPT: &str = "describe the dashcam clip";

/// Frames decoded from an H.264 clip that the `ffmpeg` CLI makes (the media layer's job in
/// production; here the CLI keeps this crate free of FFmpeg bindings). Synthetic frames when
/// the CLI is missing, so the test still covers the model path.
fn clip_frames(dir: &Path) -> Vec<Frame> {
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
    if made {
        let bytes = std::fs::read(&raw).unwrap();
        assert!(
            bytes.len() >= frame_len * n,
            "decoded {} bytes",
            bytes.len()
        );
        return bytes
            .chunks_exact(frame_len)
            .take(n)
            .enumerate()
            .map(|(i, c)| Frame {
                width: w,
                height: h,
                rgb: c.to_vec(),
                pts_s: i as f64 / 5.0,
            })
            .collect();
    }
    eprintln!("ffmpeg CLI unavailable: using synthetic frames");
    (0..n)
        .map(|k| Frame {
            width: w,
            height: h,
            rgb: (0..frame_len)
                .map(|i| ((i * 13 + k * 41) % 256) as u8)
                .collect(),
            pts_s: k as f64 / 5.0,
        })
        .collect()
}

fn config(name: &str, weights: WeightSource) -> CandleVlmConfig {
    CandleVlmConfig {
        max_new_tokens: 8,
        prompt: PROMPT.into(),
        // The test clip is 40x24; keep it at that size instead of upscaling to the default floor.
        min_pixels: 16,
        ..CandleVlmConfig::new(name, weights)
    }
}

/// The reporter as the service runs it: behind its worker thread and queue.
fn pooled(r: CandleVlmReporter) -> Arc<BackendPool<CandleVlmReporter>> {
    let name = r.name().to_string();
    Arc::new(BackendPool::new(name, Arc::new(r), PoolConfig::default()).unwrap())
}

fn clip(dir: &Path) -> ClipInput {
    ClipInput {
        path: dir.join("clip.mp4"),
        frames: clip_frames(dir).into(),
        meta: ClipMeta::default(),
    }
}

#[tokio::test]
async fn generates_deterministically_from_local_sharded_and_hf_cache() {
    let tmp = tempfile::tempdir().unwrap();
    let tiny = TinyQwen3Vl::default();
    let model_dir = tmp.path().join("model");
    tiny.write(&model_dir, 7).unwrap();
    let clip = clip(tmp.path());

    let t0 = Instant::now();
    let local =
        pooled(CandleVlmReporter::load(config("local", WeightSource::local(&model_dir))).unwrap());
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
    // 5 frames padded to 6 = 3 temporal groups of (24/4)x(40/4) patches, merged 2x2.
    assert_eq!(g.visual_tokens, 3 * 6 * 10 / 4);
    eprintln!(
        "tiny qwen3-vl: load {load_ms:.0} ms, run {:.0} ms, prefill {:.0} ms ({} prompt tokens), \
         {} new tokens at {:.1} tok/s: {:?}",
        a.latency_ms,
        g.prefill_ms,
        g.prompt_tokens,
        g.tokens.len(),
        g.tokens_per_s(),
        a.text
    );

    // Same weights through a sharded checkpoint and through the HF cache layout.
    let sharded_dir = tmp.path().join("sharded");
    tiny.write_sharded(&sharded_dir, 7).unwrap();
    let sharded = pooled(
        CandleVlmReporter::load(config("sharded", WeightSource::local(&sharded_dir))).unwrap(),
    );
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
    let hub = WeightSource::hub("tiny/qwen3-vl", "main").with_cache_dir(&cache);
    let cached = pooled(CandleVlmReporter::load(config("hub", hub)).unwrap());
    assert_eq!(cached.run(&clip).await.unwrap().text, a.text);
}

#[tokio::test]
async fn timeout_leaves_the_model_usable() {
    let tmp = tempfile::tempdir().unwrap();
    let model_dir = tmp.path().join("model");
    TinyQwen3Vl::default().write(&model_dir, 7).unwrap();
    let clip = clip(tmp.path());
    let slow = CandleVlmReporter::load(CandleVlmConfig {
        max_new_tokens: 10_000,
        ..config("slow", WeightSource::local(&model_dir))
    })
    .unwrap();
    let pool = pooled(slow);
    let r: Arc<dyn Reporter> = pool.clone();
    let t0 = Instant::now();
    let out = run_all(&[RoundReporter::new(r, Duration::from_millis(1))], &clip).await;
    assert!(matches!(out[0].1, Err(ReporterFailure::TimedOut(_))));
    assert!(t0.elapsed() < Duration::from_secs(2));
    // The cancelled generation stops at its next token and releases the model (its one worker),
    // instead of holding it for 10k tokens.
    let freed = tokio::time::timeout(
        Duration::from_secs(10),
        pool.call(|r, _| r.engine().eos_ids().to_vec()),
    )
    .await;
    assert!(freed.is_ok(), "model still busy after the timeout");
}

#[test]
fn bad_inputs_are_errors_not_panics() {
    let tmp = tempfile::tempdir().unwrap();
    let model_dir = tmp.path().join("model");
    let tiny = TinyQwen3Vl::default();
    tiny.write(&model_dir, 7).unwrap();
    let r = CandleVlmReporter::load(config("x", WeightSource::local(&model_dir))).unwrap();
    let e = r
        .generate_blocking(&[], &AtomicBool::new(false))
        .unwrap_err();
    assert_eq!(e.kind(), "invalid_input");
    let bad = Frame {
        width: 4,
        height: 4,
        rgb: vec![0; 5],
        pts_s: 0.0,
    };
    assert_eq!(
        r.generate_blocking(&[bad], &AtomicBool::new(false))
            .unwrap_err()
            .kind(),
        "invalid_input"
    );

    // A checkpoint missing a tensor fails at load, naming it.
    let broken = tmp.path().join("broken");
    tiny.write(&broken, 7).unwrap();
    let mut t =
        candle_core::safetensors::load(broken.join("model.safetensors"), &Device::Cpu).unwrap();
    t.remove("model.language_model.layers.1.mlp.up_proj.weight");
    candle_core::safetensors::save(&t, broken.join("model.safetensors")).unwrap();
    let e = match CandleVlmReporter::load(config("b", WeightSource::local(&broken))) {
        Err(e) => e,
        Ok(_) => panic!("loaded a model with a missing tensor"),
    };
    assert!(matches!(e, ModelError::BadWeights { .. }), "{e}");
    assert!(e.to_string().contains("up_proj"), "{e}");

    let e = match CandleVlmReporter::load(config("m", WeightSource::local(tmp.path()))) {
        Err(e) => e,
        Ok(_) => panic!("loaded from an empty dir"),
    };
    assert_eq!(e.kind(), "missing_weights");
}

fn mat(t: &Tensor) -> Vec<Vec<f32>> {
    t.to_dtype(DType::F32).unwrap().to_vec2::<f32>().unwrap()
}

#[test]
fn lora_adapter_is_merged_on_real_key_names() {
    let tmp = tempfile::tempdir().unwrap();
    let tiny = TinyQwen3Vl::default();
    let model_dir = tmp.path().join("model");
    let adapter_dir = tmp.path().join("adapter");
    tiny.write(&model_dir, 7).unwrap();
    let (r, alpha) = (2usize, 8.0f64);
    let adapter = tiny.write_lora_adapter(&adapter_dir, r, alpha, 99).unwrap();
    let frames = clip_frames(tmp.path());
    let refs: Vec<_> = frames.iter().map(Frame::as_ref).collect();

    let base = CandleVlmReporter::load(config("base", WeightSource::local(&model_dir))).unwrap();
    let tuned = CandleVlmReporter::load(CandleVlmConfig {
        adapter: Some(WeightSource::local(&adapter_dir)),
        ..config("tuned", WeightSource::local(&model_dir))
    })
    .unwrap();
    let base = base.engine();
    let tuned = tuned.engine();
    assert_eq!(tuned.merged_lora_keys().len(), 2 * tiny.layers);
    assert!(base.merged_lora_keys().is_empty());

    // W = W0 + (alpha/r)·B·A, by hand, for one targeted module.
    let key = "model.language_model.layers.1.self_attn.v_proj.weight";
    let pre = "base_model.model.model.language_model.layers.1.self_attn.v_proj";
    let w0 = mat(base.tensor(key).unwrap());
    let a = mat(&adapter[&format!("{pre}.lora_A.weight")]);
    let b = mat(&adapter[&format!("{pre}.lora_B.weight")]);
    let w = mat(tuned.tensor(key).unwrap());
    let s = (alpha / r as f64) as f32;
    let mut max_delta = 0f32;
    for (o, row) in w.iter().enumerate() {
        for (i, &got) in row.iter().enumerate() {
            let delta: f32 = (0..r).map(|k| b[o][k] * a[k][i]).sum::<f32>() * s;
            let want = w0[o][i] + delta;
            assert!((got - want).abs() < 1e-5, "[{o},{i}] {got} vs {want}");
            max_delta = max_delta.max(delta.abs());
        }
    }
    assert!(max_delta > 0.1, "adapter delta too small to test anything");
    // Untargeted modules stay as they were.
    let k = "model.language_model.layers.1.self_attn.k_proj.weight";
    assert_eq!(mat(base.tensor(k).unwrap()), mat(tuned.tensor(k).unwrap()));

    // And the merged weights are what the forward pass uses.
    let lb = base.first_token_logits(&refs, PROMPT, true).unwrap();
    let lt = tuned.first_token_logits(&refs, PROMPT, true).unwrap();
    assert_eq!(lb.len(), tiny.vocab_size());
    let diff = lb
        .iter()
        .zip(&lt)
        .map(|(x, y)| (x - y).abs())
        .fold(0f32, f32::max);
    assert!(
        diff > 1e-3,
        "adapter did not change the logits (max diff {diff})"
    );

    // The one-chunk prefill runs too (different numbers: candle attends bidirectionally there).
    let lc = base.first_token_logits(&refs, PROMPT, false).unwrap();
    assert!(lc.iter().all(|x| x.is_finite()));
}
