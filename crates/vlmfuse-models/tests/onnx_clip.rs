//! The CLIP embedder on ONNX Runtime against torch (expected outputs committed by
//! `scripts/onnx/make_fixtures.py`) and against the candle backend on the same weights, on the
//! tiny random-weight exports under `tests/data/onnx/`.

use std::path::{Path, PathBuf};

use candle_core::Device;
use vlmfuse_models::imaging::ImageProcessor;
use vlmfuse_models::{
    ClipEmbedder, ContextEmbedder, FrameRef, OnnxClipConfig, OnnxClipEmbedder, WeightSource,
};
use vlmfuse_ort::SessionOptions;
use vlmfuse_testkit_models::assets::require_onnxruntime;
use vlmfuse_testkit_models::fixtures::write_hf_cache_entry;

fn data(rel: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../tests/data/onnx")
        .join(rel)
}

/// ONNX Runtime's library from the asset cache; panics, naming the fetch script, when missing
/// (the tests that call it are `#[ignore]`d unless the test command fetched the assets).
fn runtime() {
    require_onnxruntime();
}

fn frame(seed: u32, w: u32, h: u32) -> Vec<u8> {
    (0..w * h * 3)
        .map(|i| {
            (i.wrapping_mul(2_654_435_761)
                .wrapping_add(seed.wrapping_mul(97))
                >> 7) as u8
        })
        .collect()
}

struct Expected {
    frames: Vec<(u32, Vec<u8>, u32, u32)>,
    image_embeds: Vec<Vec<f32>>,
    clip_embedding: Vec<f32>,
}

impl Expected {
    fn load(dir: &str) -> Self {
        let v: serde_json::Value = serde_json::from_str(
            &std::fs::read_to_string(data(dir).join("expected.json")).unwrap(),
        )
        .unwrap();
        let floats = |v: &serde_json::Value| -> Vec<f32> {
            v.as_array()
                .unwrap()
                .iter()
                .map(|x| x.as_f64().unwrap() as f32)
                .collect()
        };
        let frames = v["frames"]
            .as_array()
            .unwrap()
            .iter()
            .map(|f| {
                let (s, w, h) = (
                    f["seed"].as_u64().unwrap() as u32,
                    f["width"].as_u64().unwrap() as u32,
                    f["height"].as_u64().unwrap() as u32,
                );
                (s, frame(s, w, h), w, h)
            })
            .collect();
        Self {
            frames,
            image_embeds: v["image_embeds"]
                .as_array()
                .unwrap()
                .iter()
                .map(floats)
                .collect(),
            clip_embedding: floats(&v["clip_embedding"]),
        }
    }

    fn refs(&self) -> Vec<FrameRef<'_>> {
        self.frames
            .iter()
            .map(|(_, rgb, w, h)| FrameRef {
                width: *w,
                height: *h,
                rgb,
            })
            .collect()
    }
}

/// What CLIPImageProcessor made of the fixture frames, `[4, 3, 32, 32]`.
fn hf_pixels() -> Vec<f32> {
    std::fs::read(data("tiny-clip/pixel_values.f32"))
        .unwrap()
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes(b.try_into().unwrap()))
        .collect()
}

fn cosine(a: &[f32], b: &[f32]) -> f64 {
    assert_eq!(a.len(), b.len());
    let dot: f64 = a.iter().zip(b).map(|(x, y)| *x as f64 * *y as f64).sum();
    let na: f64 = a.iter().map(|x| (*x as f64).powi(2)).sum::<f64>().sqrt();
    let nb: f64 = b.iter().map(|x| (*x as f64).powi(2)).sum::<f64>().sqrt();
    dot / (na * nb)
}

fn max_abs(a: &[f32], b: &[f32]) -> f32 {
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max)
}

fn load(dir: &Path) -> OnnxClipEmbedder {
    OnnxClipEmbedder::load(&OnnxClipConfig::new(WeightSource::local(dir))).unwrap()
}

#[test]
fn preprocessing_equals_clip_image_processor() {
    // No runtime needed: the pixels the ONNX backend feeds are transformers' own.
    let exp = Expected::load("tiny-clip");
    let hf = hf_pixels();
    let p = ImageProcessor::clip(32);
    for (k, f) in exp.refs().into_iter().enumerate() {
        let mut out = vec![0f32; 3 * 32 * 32];
        p.process_into(f, &mut out).unwrap();
        let d = max_abs(&out, &hf[k * 3072..(k + 1) * 3072]);
        // Float rounding only: one grey level is 1/255/0.27 ≈ 0.0146 here.
        assert!(
            d < 1e-4,
            "frame {k} ({}x{}): max diff {d}",
            f.width,
            f.height
        );
    }
}

#[test]
#[ignore = "needs assets: scripts/fetch-assets.sh"]
fn vision_export_matches_torch() {
    runtime();
    let exp = Expected::load("tiny-clip");
    let emb = load(&data("tiny-clip"));
    assert_eq!(emb.dim(), 16);
    assert_eq!(emb.input_size(), (32, 32));
    assert!(!emb.per_frame_normalised());
    assert!(emb.model_path().ends_with("onnx/vision_model.onnx"));
    assert!(emb.name().starts_with("clip-onnx:"), "{}", emb.name());

    // The graph alone, on torch's own pixels.
    let rows = emb.pixel_embeddings(&hf_pixels(), 4).unwrap();
    for (k, (got, want)) in rows.iter().zip(&exp.image_embeds).enumerate() {
        let c = cosine(got, want);
        assert!(c >= 0.99999, "frame {k}: cosine {c}");
        assert!(
            max_abs(got, want) < 1e-4,
            "frame {k}: {}",
            max_abs(got, want)
        );
    }
    // End to end from RGB frames (including a 1280x720 one).
    let e = emb.embed(&exp.refs()).unwrap();
    let c = cosine(&e, &exp.clip_embedding);
    assert!(c >= 0.99999, "clip embedding cosine {c}");
    let norm: f32 = e.iter().map(|x| x * x).sum::<f32>().sqrt();
    assert!((norm - 1.0).abs() < 1e-6, "norm {norm}");
    // Deterministic, and one frame alone gives its own row.
    assert_eq!(e, emb.embed(&exp.refs()).unwrap());
    let one = emb.frame_embeddings(&exp.refs()[2..3]).unwrap();
    assert!(max_abs(&one[0], &rows[2]) < 1e-5);
}

#[test]
#[ignore = "needs assets: scripts/fetch-assets.sh"]
fn same_weights_as_candle_give_the_same_embeddings() {
    runtime();
    let exp = Expected::load("tiny-clip");
    let dir = data("tiny-clip");
    let onnx = load(&dir);
    let candle = ClipEmbedder::load(&WeightSource::local(&dir), &Device::Cpu).unwrap();
    assert_eq!(candle.dim(), onnx.dim());
    let frames = exp.refs();

    // Same pixels (the candle backend's own preprocessing) through both engines.
    let mut px = Vec::new();
    for f in &frames {
        px.extend(ImageProcessor::clip(32).apply(*f).unwrap().0);
    }
    let ours = onnx.pixel_embeddings(&px, frames.len()).unwrap();
    let theirs = candle
        .frame_embeddings(&frames)
        .unwrap()
        .to_vec2::<f32>()
        .unwrap();
    for (k, (a, b)) in ours.iter().zip(&theirs).enumerate() {
        let c = cosine(a, b);
        assert!(c >= 0.99999, "frame {k}: ort vs candle cosine {c}");
    }
    let c = cosine(
        &onnx.embed_pixels(&px, frames.len()).unwrap(),
        &candle.embed(&frames).unwrap(),
    );
    assert!(c >= 0.99999, "clip embedding ort vs candle: {c}");

    // Each backend with its own preprocessing (one image module: the same pixels), so the
    // clip embeddings agree closely.
    let c = cosine(
        &onnx.embed(&frames).unwrap(),
        &candle.embed(&frames).unwrap(),
    );
    assert!(c >= 0.9999, "ort vs candle from frames: {c}");
}

#[test]
#[ignore = "needs assets: scripts/fetch-assets.sh"]
fn whole_clipmodel_export_runs_with_constant_text_inputs() {
    runtime();
    let exp = Expected::load("tiny-clip-full");
    let emb = load(&data("tiny-clip-full"));
    assert!(emb.model_path().ends_with("model.onnx"));
    assert!(emb.per_frame_normalised());
    assert_eq!(emb.dim(), 16);
    let rows = emb.pixel_embeddings(&hf_pixels(), 4).unwrap();
    for (k, (got, want)) in rows.iter().zip(&exp.image_embeds).enumerate() {
        assert!(cosine(got, want) >= 0.99999, "frame {k}");
        assert!(max_abs(got, want) < 1e-4, "frame {k}");
    }
    let c = cosine(&emb.embed(&exp.refs()).unwrap(), &exp.clip_embedding);
    assert!(c >= 0.99999, "{c}");
}

fn copy_dir(from: &Path, to: &Path, files: &[(&str, &str)]) {
    for (src, dst) in files {
        let d = to.join(dst);
        std::fs::create_dir_all(d.parent().unwrap()).unwrap();
        std::fs::copy(from.join(src), d).unwrap();
    }
}

#[test]
#[ignore = "needs assets: scripts/fetch-assets.sh"]
fn layouts_named_files_hub_cache_and_thread_counts() {
    runtime();
    let src = data("tiny-clip");
    let exp = Expected::load("tiny-clip");
    let want = load(&src).embed(&exp.refs()).unwrap();

    // A top-level model.onnx (Optimum's name for a vision export).
    let flat = tempfile::tempdir().unwrap();
    copy_dir(
        &src,
        flat.path(),
        &[
            ("onnx/vision_model.onnx", "model.onnx"),
            ("preprocessor_config.json", "preprocessor_config.json"),
        ],
    );
    let e = load(flat.path());
    assert!(e.model_path().ends_with("model.onnx"));
    assert_eq!(e.embed(&exp.refs()).unwrap(), want);

    // A named file, relative to the directory.
    let named = tempfile::tempdir().unwrap();
    copy_dir(
        &src,
        named.path(),
        &[
            ("onnx/vision_model.onnx", "onnx/vision_model_fp32.onnx"),
            ("preprocessor_config.json", "preprocessor_config.json"),
        ],
    );
    let cfg = OnnxClipConfig {
        model_file: Some("onnx/vision_model_fp32.onnx".into()),
        ..OnnxClipConfig::new(WeightSource::local(named.path()))
    };
    assert_eq!(
        OnnxClipEmbedder::load(&cfg)
            .unwrap()
            .embed(&exp.refs())
            .unwrap(),
        want
    );

    // The HF cache (snapshot entries are symlinks into blobs/), Optimum's layout.
    let cache = tempfile::tempdir().unwrap();
    write_hf_cache_entry(
        cache.path(),
        "Xenova/clip-tiny",
        "main",
        &"b".repeat(40),
        flat.path(),
        &["model.onnx", "preprocessor_config.json"],
    )
    .unwrap();
    let hub = WeightSource::hub("Xenova/clip-tiny", "main")
        .with_cache_dir(cache.path())
        .offline();
    let e = OnnxClipEmbedder::load(&OnnxClipConfig::new(hub)).unwrap();
    assert_eq!(e.name(), "clip-onnx:hf:Xenova/clip-tiny@main");
    assert_eq!(e.embed(&exp.refs()).unwrap(), want);

    // The pool size changes nothing but speed.
    for threads in [1, 3] {
        let cfg = OnnxClipConfig {
            session: SessionOptions::with_threads(threads),
            ..OnnxClipConfig::new(WeightSource::local(&src))
        };
        let e = OnnxClipEmbedder::load(&cfg).unwrap();
        assert_eq!(e.threads(), threads);
        let got = e.embed(&exp.refs()).unwrap();
        assert!(cosine(&got, &want) > 0.9999999, "threads {threads}");
    }
}

#[test]
#[ignore = "needs assets: scripts/fetch-assets.sh"]
fn bad_models_and_inputs_are_clear_errors() {
    runtime();
    let src = data("tiny-clip");

    // Nothing to load: every place looked at is named.
    let empty = tempfile::tempdir().unwrap();
    let e = OnnxClipEmbedder::load(&OnnxClipConfig::new(WeightSource::local(empty.path())))
        .unwrap_err();
    assert_eq!(e.kind(), "missing_weights", "{e}");
    assert!(e.to_string().contains("onnx/vision_model.onnx"), "{e}");

    // Not an ONNX file.
    let junk = tempfile::tempdir().unwrap();
    std::fs::write(junk.path().join("model.onnx"), b"not a model").unwrap();
    let e =
        OnnxClipEmbedder::load(&OnnxClipConfig::new(WeightSource::local(junk.path()))).unwrap_err();
    assert_eq!(e.kind(), "bad_model", "{e}");
    assert!(e.to_string().contains("model.onnx"), "{e}");

    // A valid ONNX model that is not an image encoder (the tiny BERT).
    let bert = tempfile::tempdir().unwrap();
    copy_dir(
        &data("tiny-bert"),
        bert.path(),
        &[("model.onnx", "model.onnx")],
    );
    let e =
        OnnxClipEmbedder::load(&OnnxClipConfig::new(WeightSource::local(bert.path()))).unwrap_err();
    assert_eq!(e.kind(), "bad_model", "{e}");
    assert!(e.to_string().contains("token_type_ids"), "{e}");

    // Preprocessing that does not fit the model's input.
    let mismatch = tempfile::tempdir().unwrap();
    copy_dir(
        &src,
        mismatch.path(),
        &[("onnx/vision_model.onnx", "onnx/vision_model.onnx")],
    );
    std::fs::write(
        mismatch.path().join("preprocessor_config.json"),
        r#"{"size": {"shortest_edge": 64}, "crop_size": {"height": 64, "width": 64}}"#,
    )
    .unwrap();
    let e = OnnxClipEmbedder::load(&OnnxClipConfig::new(WeightSource::local(mismatch.path())))
        .unwrap_err();
    assert_eq!(e.kind(), "bad_config", "{e}");
    assert!(
        e.to_string().contains("64x64") && e.to_string().contains("32x32"),
        "{e}"
    );

    // Malformed preprocessor config.
    std::fs::write(mismatch.path().join("preprocessor_config.json"), "{").unwrap();
    let e = OnnxClipEmbedder::load(&OnnxClipConfig::new(WeightSource::local(mismatch.path())))
        .unwrap_err();
    assert_eq!(e.kind(), "bad_config", "{e}");

    // No preprocessor config: CLIP's defaults at the model's input size.
    std::fs::remove_file(mismatch.path().join("preprocessor_config.json")).unwrap();
    let e =
        OnnxClipEmbedder::load(&OnnxClipConfig::new(WeightSource::local(mismatch.path()))).unwrap();
    assert_eq!(e.processor(), &ImageProcessor::clip(32));

    // Bad frames.
    let emb = load(&src);
    assert_eq!(emb.embed(&[]).unwrap_err().kind(), "invalid_input");
    let short = [0u8; 5];
    let bad = FrameRef {
        width: 4,
        height: 4,
        rgb: &short,
    };
    assert_eq!(emb.embed(&[bad]).unwrap_err().kind(), "invalid_input");
    assert_eq!(
        emb.pixel_embeddings(&[0.0; 10], 1).unwrap_err().kind(),
        "invalid_input"
    );
}
