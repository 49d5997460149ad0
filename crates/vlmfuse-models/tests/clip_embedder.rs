//! The CLIP embedder loaded from tiny random-weight checkpoints in the real HF layout.

use candle_core::Device;
use vlmfuse_models::{ClipEmbedder, ContextEmbedder, FrameRef, WeightSource};
use vlmfuse_testkit_models::fixtures::{write_hf_cache_entry, TinyClip};

fn frame(seed: u32, w: u32, h: u32) -> Vec<u8> {
    (0..w * h * 3)
        .map(|i| {
            (i.wrapping_mul(2_654_435_761)
                .wrapping_add(seed.wrapping_mul(97))
                >> 7) as u8
        })
        .collect()
}

fn norm(v: &[f32]) -> f32 {
    v.iter().map(|x| x * x).sum::<f32>().sqrt()
}

#[test]
fn local_dir_embedding_is_unit_norm_deterministic_and_discriminative() {
    let tmp = tempfile::tempdir().unwrap();
    let spec = TinyClip::default();
    spec.write(tmp.path(), 7).unwrap();
    let emb = ClipEmbedder::load(&WeightSource::local(tmp.path()), &Device::Cpu).unwrap();
    assert_eq!(emb.dim(), 16);
    assert!(emb.name().starts_with("clip:"));

    let (a, b, c) = (frame(1, 64, 40), frame(2, 64, 40), frame(3, 50, 50));
    let fa = FrameRef {
        width: 64,
        height: 40,
        rgb: &a,
    };
    let fb = FrameRef {
        width: 64,
        height: 40,
        rgb: &b,
    };
    let fc = FrameRef {
        width: 50,
        height: 50,
        rgb: &c,
    };

    let e1 = emb.embed(&[fa, fb, fc]).unwrap();
    assert_eq!(e1.len(), 16);
    assert!((norm(&e1) - 1.0).abs() < 1e-5, "norm {}", norm(&e1));
    assert!(e1.iter().all(|x| x.is_finite()));

    let e2 = emb.embed(&[fa, fb, fc]).unwrap();
    assert_eq!(e1, e2, "same frames must give the identical vector");

    let e3 = emb.embed(&[fc]).unwrap();
    let dist: f32 = e1
        .iter()
        .zip(&e3)
        .map(|(x, y)| (x - y).powi(2))
        .sum::<f32>()
        .sqrt();
    assert!(
        dist > 1e-3,
        "different frames gave (nearly) the same vector: {dist}"
    );

    // A clip embedding is the normalised mean of frame embeddings: check against the per-frame
    // outputs, which also proves the batch is not mixed across frames.
    let per = emb
        .frame_embeddings(&[fa, fb, fc])
        .unwrap()
        .to_vec2::<f32>()
        .unwrap();
    let single = emb
        .frame_embeddings(&[fc])
        .unwrap()
        .to_vec2::<f32>()
        .unwrap();
    for (x, y) in per[2].iter().zip(&single[0]) {
        assert!(
            (x - y).abs() < 1e-4,
            "batched vs single frame differ: {x} {y}"
        );
    }
    let mut mean = vec![0f32; 16];
    for row in &per {
        for (m, v) in mean.iter_mut().zip(row) {
            *m += v / 3.0;
        }
    }
    let n = norm(&mean);
    for (m, e) in mean.iter().zip(&e1) {
        assert!((m / n - e).abs() < 1e-5);
    }

    // A different checkpoint (seed) must give a different embedding of the same frames.
    let tmp2 = tempfile::tempdir().unwrap();
    spec.write(tmp2.path(), 8).unwrap();
    let emb2 = ClipEmbedder::load(&WeightSource::local(tmp2.path()), &Device::Cpu).unwrap();
    assert_ne!(emb2.embed(&[fa, fb, fc]).unwrap(), e1);
}

#[test]
fn hub_cache_layout_loads_the_same_model() {
    let src = tempfile::tempdir().unwrap();
    TinyClip::default().write(src.path(), 7).unwrap();
    let cache = tempfile::tempdir().unwrap();
    let commit = "a".repeat(40);
    write_hf_cache_entry(
        cache.path(),
        "openai/clip-tiny",
        "main",
        &commit,
        src.path(),
        &["config.json", "model.safetensors"],
    )
    .unwrap();
    let hub = WeightSource::hub("openai/clip-tiny", "main")
        .with_cache_dir(cache.path())
        .offline();
    let from_hub = ClipEmbedder::load(&hub, &Device::Cpu).unwrap();
    let local = ClipEmbedder::load(&WeightSource::local(src.path()), &Device::Cpu).unwrap();
    assert_eq!(from_hub.name(), "clip:hf:openai/clip-tiny@main");
    let px = frame(5, 32, 32);
    let f = [FrameRef {
        width: 32,
        height: 32,
        rgb: &px,
    }];
    assert_eq!(from_hub.embed(&f).unwrap(), local.embed(&f).unwrap());

    let wrong = WeightSource::hub("openai/clip-tiny", "v9")
        .with_cache_dir(cache.path())
        .offline();
    let e = ClipEmbedder::load(&wrong, &Device::Cpu).err().unwrap();
    assert_eq!(e.kind(), "missing_weights");
    assert!(e.to_string().contains("refs/v9"), "{e}");
}

#[test]
fn missing_and_corrupt_weights_are_clear_errors() {
    let tmp = tempfile::tempdir().unwrap();
    TinyClip::default().write(tmp.path(), 1).unwrap();
    let st = tmp.path().join("model.safetensors");

    let bytes = std::fs::read(&st).unwrap();
    std::fs::write(&st, &bytes[..bytes.len() / 2]).unwrap();
    let e = ClipEmbedder::load(&WeightSource::local(tmp.path()), &Device::Cpu)
        .err()
        .unwrap();
    assert_eq!(e.kind(), "bad_weights", "{e}");
    assert!(e.to_string().contains("model.safetensors"), "{e}");

    std::fs::remove_file(&st).unwrap();
    let e = ClipEmbedder::load(&WeightSource::local(tmp.path()), &Device::Cpu)
        .err()
        .unwrap();
    assert_eq!(e.kind(), "missing_weights", "{e}");
    assert!(e.to_string().contains(&st.display().to_string()), "{e}");
}

#[test]
fn wrong_shapes_and_missing_tensors_are_refused() {
    // Checkpoint written for projection 16, config claims 24: shape mismatch must not load.
    let tmp = tempfile::tempdir().unwrap();
    TinyClip::default().write(tmp.path(), 1).unwrap();
    let cfg = TinyClip {
        projection_dim: 24,
        ..Default::default()
    }
    .config_json();
    std::fs::write(tmp.path().join("config.json"), cfg.to_string()).unwrap();
    let e = ClipEmbedder::load(&WeightSource::local(tmp.path()), &Device::Cpu)
        .err()
        .unwrap();
    assert_eq!(e.kind(), "bad_weights", "{e}");

    // No class embedding: candle would invent a random one; we must refuse.
    let tmp = tempfile::tempdir().unwrap();
    let spec = TinyClip::default();
    let mut t = spec.tensors(1);
    t.remove("vision_model.embeddings.class_embedding");
    std::fs::write(
        tmp.path().join("config.json"),
        spec.config_json().to_string(),
    )
    .unwrap();
    candle_core::safetensors::save(&t, tmp.path().join("model.safetensors")).unwrap();
    let e = ClipEmbedder::load(&WeightSource::local(tmp.path()), &Device::Cpu)
        .err()
        .unwrap();
    assert!(e.to_string().contains("class_embedding"), "{e}");

    // Unsupported activation.
    let mut cfg = spec.config_json();
    cfg["vision_config"]["hidden_act"] = "gelu".into();
    std::fs::write(tmp.path().join("config.json"), cfg.to_string()).unwrap();
    let e = ClipEmbedder::load(&WeightSource::local(tmp.path()), &Device::Cpu)
        .err()
        .unwrap();
    assert_eq!(e.kind(), "bad_config", "{e}");
}

#[test]
fn empty_or_malformed_frames_are_input_errors() {
    let tmp = tempfile::tempdir().unwrap();
    TinyClip::default().write(tmp.path(), 1).unwrap();
    let emb = ClipEmbedder::load(&WeightSource::local(tmp.path()), &Device::Cpu).unwrap();
    assert_eq!(emb.embed(&[]).unwrap_err().kind(), "invalid_input");
    let short = [0u8; 5];
    let e = emb
        .embed(&[FrameRef {
            width: 4,
            height: 4,
            rgb: &short,
        }])
        .unwrap_err();
    assert_eq!(e.kind(), "invalid_input");
}

#[test]
fn a_config_written_by_transformers_loads() {
    // transformers writes CLIPVisionConfig's default `projection_dim: 512` inside
    // `vision_config` beside the real top-level value (16 here), and CLIPModel sizes
    // `visual_projection` from the top-level one (tests/data/make_clip_transformers_config.py).
    let tmp = tempfile::tempdir().unwrap();
    TinyClip::default().write(tmp.path(), 3).unwrap();
    let cfg = include_str!("data/clip_transformers_config.json");
    let parsed: serde_json::Value = serde_json::from_str(cfg).unwrap();
    assert_eq!(parsed["vision_config"]["projection_dim"], 512);
    std::fs::write(tmp.path().join("config.json"), cfg).unwrap();

    let emb = ClipEmbedder::load(&WeightSource::local(tmp.path()), &Device::Cpu)
        .unwrap_or_else(|e| panic!("transformers' own config must load: {e}"));
    assert_eq!(emb.dim(), 16);
    assert_eq!(emb.settings().projection_dim, 16);
    let f = frame(5, 40, 30);
    let v = emb
        .embed(&[FrameRef {
            width: 40,
            height: 30,
            rgb: &f,
        }])
        .unwrap();
    assert_eq!(v.len(), 16);

    // The same embedder as from TinyClip's own config, which states 16 in both places.
    let own = tempfile::tempdir().unwrap();
    TinyClip::default().write(own.path(), 3).unwrap();
    let reference = ClipEmbedder::load(&WeightSource::local(own.path()), &Device::Cpu).unwrap();
    let w = reference
        .embed(&[FrameRef {
            width: 40,
            height: 30,
            rgb: &f,
        }])
        .unwrap();
    assert_eq!(v, w);
}
