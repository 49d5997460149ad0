//! VideoLLaMA2 against the DAMO-NLP-SG/VideoLLaMA2 repository's own code (transformers 4.40,
//! timm 1.0.3) on the tiny fixtures: frame choice and preprocessing (padded to square and
//! not), the chat prompt and its tokens, first-token logits, 16 greedy ids, and a LoRA run
//! with its `non_lora_trainables.bin`, compared with the outputs `scripts/parity/videollama2.py`
//! stored under `tests/data/parity/videollama2/`. The fixtures are rebuilt here by the same
//! deterministic writer the script read.

use std::path::PathBuf;

use vlmfuse_models::generate::{generate_with, GenerateOptions};
use vlmfuse_models::models::family::{load_family, FamilyOptions};
use vlmfuse_models::models::videollama2::{
    LoadOptions, ModelInputs, VideoLlama2, VideoLlama2Processor, VISUAL_TOKEN,
};
use vlmfuse_models::{Frame, FrameRef, ModelError, WeightSource};
use vlmfuse_testkit_models::fixtures::video_llava::{SyntheticClip, PARITY_CLIPS};
use vlmfuse_testkit_models::fixtures::TinyVideoLlama2;
use vlmfuse_testkit_models::parity::{b64, f32s, max_abs_diff};

const MODEL_SEED: u64 = 5;
const ADAPTER_SEED: u64 = 23;
const TOL: f32 = 1e-4;

fn read_json(name: &str) -> serde_json::Value {
    vlmfuse_testkit_models::parity::read_reference(
        "videollama2",
        name,
        "scripts/parity/videollama2.py",
    )
}

/// The fixture directories, as `examples/videollama2_fixture.rs` lays them out.
struct Fixture {
    _tmp: tempfile::TempDir,
    root: PathBuf,
}

fn fixture() -> Fixture {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path().to_path_buf();
    let base = TinyVideoLlama2::default();
    base.write(&root.join("mistral-base"), MODEL_SEED).unwrap();
    TinyVideoLlama2 {
        aspect_ratio: "no",
        ..TinyVideoLlama2::default()
    }
    .write(&root.join("mistral-crop"), MODEL_SEED)
    .unwrap();
    TinyVideoLlama2 {
        no_template: true,
        ..TinyVideoLlama2::default()
    }
    .write(&root.join("mistral-notemplate"), MODEL_SEED)
    .unwrap();
    let base_dir = std::fs::canonicalize(root.join("mistral-base")).unwrap();
    base.write_lora_run(
        &root.join("videollama2-lora"),
        &base_dir,
        4,
        8.0,
        ADAPTER_SEED,
    )
    .unwrap();
    Fixture { _tmp: tmp, root }
}

/// Loads a fixture variant (`videollama2-lora`: the base with the run merged).
fn load(fx: &Fixture, variant: &str) -> (VideoLlama2, VideoLlama2Processor) {
    let (dir, adapter) = if variant == "videollama2-lora" {
        (
            fx.root.join("mistral-base"),
            Some(WeightSource::local(fx.root.join(variant))),
        )
    } else {
        (fx.root.join(variant), None)
    };
    let src = WeightSource::local(&dir);
    let (model, tower) = VideoLlama2::load(
        &src,
        &LoadOptions {
            adapter,
            ..LoadOptions::default()
        },
    )
    .unwrap();
    let proc = VideoLlama2Processor::load(&src, model.config(), &tower.preprocessor).unwrap();
    (model, proc)
}

fn clip(name: &str) -> &'static SyntheticClip {
    PARITY_CLIPS.iter().find(|c| c.name == name).unwrap()
}

fn prompt(key: &str) -> &'static str {
    match key {
        "describe" => "Describe the dashcam clip.",
        "manoeuvre" => "What should the car do? Scene: Manoeuvres: Rationale:",
        other => panic!("unknown prompt {other}"),
    }
}

fn refs(frames: &[Frame]) -> Vec<FrameRef<'_>> {
    frames.iter().map(|f| f.as_ref()).collect()
}

fn inputs(
    model: &VideoLlama2,
    proc: &VideoLlama2Processor,
    clip_name: &str,
    p: &str,
) -> ModelInputs {
    let frames = clip(clip_name).render();
    let r = refs(&frames);
    let v = proc.preprocess_video(&r).unwrap();
    let text = proc.prompt(prompt(p)).unwrap();
    let ids = proc
        .encode(&text, model.config().tokens_per_clip(v.frames))
        .unwrap();
    ModelInputs {
        ids: proc.pad_left(vec![ids]),
        videos: vec![v],
    }
}

/// Our ids with each clip's run of visual tokens folded back into the repository's `-201`.
fn folded(ids: &[u32]) -> Vec<i64> {
    let mut out = Vec::new();
    for (i, &t) in ids.iter().enumerate() {
        if t == VISUAL_TOKEN {
            if i == 0 || ids[i - 1] != VISUAL_TOKEN {
                out.push(-201);
            }
        } else {
            out.push(t as i64);
        }
    }
    out
}

#[test]
fn frames_and_preprocessing_match_the_repository_to_the_grey_level() {
    let fx = fixture();
    let want = read_json("preprocess.json");
    for variant in ["mistral-base", "mistral-crop"] {
        let (_, proc) = load(&fx, variant);
        for c in PARITY_CLIPS.iter() {
            let w = &want["clips"][format!("{variant}/{}", c.name)];
            let frames = c.render();
            let idx: Vec<usize> = w["indices"]
                .as_array()
                .unwrap()
                .iter()
                .map(|x| x.as_u64().unwrap() as usize)
                .collect();
            assert_eq!(
                VideoLlama2Processor::sample_indices(frames.len(), proc.num_frames),
                idx,
                "{variant}/{}: frame_sample",
                c.name
            );
            let v = proc.preprocess_video(&refs(&frames)).unwrap();
            let shape: Vec<usize> = w["shape"]
                .as_array()
                .unwrap()
                .iter()
                .map(|x| x.as_u64().unwrap() as usize)
                .collect();
            assert_eq!(vec![v.frames, 3, v.height, v.width], shape, "{}", c.name);
            // Back to grey levels (the inverse of rescale + normalize) and compared.
            let (mean, std) = (proc.image.mean, proc.image.std);
            let plane = v.height * v.width;
            let ours: Vec<u8> = v
                .data
                .iter()
                .enumerate()
                .map(|(i, &x)| {
                    let ch = (i / plane) % 3;
                    (x as f64 * std[ch] * 255.0 + mean[ch] * 255.0)
                        .round()
                        .clamp(0.0, 255.0) as u8
                })
                .collect();
            let theirs = b64(&w["u8"]);
            let worst = ours
                .iter()
                .zip(&theirs)
                .map(|(a, b)| (*a as i32 - *b as i32).abs())
                .max()
                .unwrap();
            assert!(worst <= 1, "{variant}/{}: {worst} grey levels off", c.name);
            if let Some(f0) = w.get("f32_frame0") {
                let n = 3 * plane;
                let d = max_abs_diff(&v.data[..n], &f32s(f0));
                assert!(d < 1e-5, "{variant}/{}: frame 0 off by {d}", c.name);
            }
        }
    }
}

#[test]
fn prompt_ids_logits_and_greedy_ids_match_the_repository() {
    let fx = fixture();
    let want = read_json("cases.json");
    let mut loaded: Vec<(String, VideoLlama2, VideoLlama2Processor)> = Vec::new();
    let mut checked = 0;
    for case in want["cases"].as_array().unwrap() {
        let variant = case["model"].as_str().unwrap();
        if !loaded.iter().any(|(v, _, _)| v == variant) {
            let (m, p) = load(&fx, variant);
            loaded.push((variant.to_string(), m, p));
        }
        let (_, model, proc) = loaded.iter().find(|(v, _, _)| v == variant).unwrap();
        let p = case["prompt"].as_str().unwrap();
        let text = proc.prompt(prompt(p)).unwrap();
        assert_eq!(
            text,
            case["text"].as_str().unwrap(),
            "{variant}: prompt text"
        );
        let Some(clip_name) = case["clip"].as_str() else {
            // The template-less case: transformers' default LLaMA-2 template, tokens too.
            let ids = proc.encode(&text, 1).unwrap();
            let theirs: Vec<i64> = case["input_ids"]
                .as_array()
                .unwrap()
                .iter()
                .map(|x| x.as_i64().unwrap())
                .collect();
            assert_eq!(folded(&ids), theirs, "{variant}: input ids");
            continue;
        };
        let inp = inputs(model, proc, clip_name, p);
        let theirs: Vec<i64> = case["input_ids"]
            .as_array()
            .unwrap()
            .iter()
            .map(|x| x.as_i64().unwrap())
            .collect();
        assert_eq!(
            folded(&inp.ids.input_ids[0]),
            theirs,
            "{variant}/{clip_name}: input ids"
        );
        assert_eq!(
            inp.ids.seq_len() as u64,
            case["prompt_len"].as_u64().unwrap(),
            "{variant}/{clip_name}: prompt length after the clip's tokens"
        );
        let mut cache = model.new_cache(inp.ids.seq_len() + 20);
        let g = generate_with(
            model,
            &inp,
            &mut cache,
            &GenerateOptions {
                keep_first_logits: true,
                ..GenerateOptions::greedy(16, &[])
            },
            None,
        )
        .unwrap();
        let first: Vec<f32> = g.first_logits[0].clone();
        let d = max_abs_diff(&first, &f32s(&case["logits"]));
        eprintln!("{variant}/{clip_name}: first-token logits max abs diff {d:.2e}");
        assert!(
            d < TOL,
            "{variant}/{clip_name}: first-token logits off by {d}"
        );
        let ids: Vec<u32> = case["greedy"]
            .as_array()
            .unwrap()
            .iter()
            .map(|x| x.as_u64().unwrap() as u32)
            .collect();
        assert_eq!(g.tokens[0], ids, "{variant}/{clip_name}: greedy ids");
        checked += 1;
    }
    assert!(checked >= 9, "only {checked} cases compared");
}

#[test]
fn the_lora_run_merges_the_adapter_and_replaces_the_connector() {
    let fx = fixture();
    let (base, proc) = load(&fx, "mistral-base");
    let (tuned, _) = load(&fx, "videollama2-lora");
    let keys = tuned.merged_lora_keys();
    assert_eq!(keys.len(), 4, "{keys:?}");
    assert!(
        keys.iter().all(|k| k.starts_with("model.layers.")),
        "{keys:?}"
    );
    // The connector comes from non_lora_trainables.bin: the clip's tokens differ.
    let inp = inputs(&base, &proc, "landscape", "describe");
    let a: Vec<f32> = base
        .video_features(&inp.videos)
        .unwrap()
        .flatten_all()
        .unwrap()
        .to_vec1()
        .unwrap();
    let b: Vec<f32> = tuned
        .video_features(&inp.videos)
        .unwrap()
        .flatten_all()
        .unwrap()
        .to_vec1()
        .unwrap();
    assert!(
        max_abs_diff(&a, &b) > 1e-2,
        "the run's connector was not loaded"
    );
}

#[test]
fn the_family_loads_by_model_type_and_describes_a_clip() {
    let fx = fixture();
    let fam = load_family(
        &WeightSource::local(fx.root.join("mistral-base")),
        &FamilyOptions {
            dtype: candle_core::DType::F32,
            device: candle_core::Device::Cpu,
            adapter: None,
            frames: None,
            prompt: prompt("describe").into(),
        },
    )
    .unwrap();
    assert_eq!(fam.model_type(), "videollama2");
    assert_eq!(fam.frames(), 4);
    // The repository's sampler over a 100-frame, 10 fps clip: frames 12, 37, 62, 87.
    let t = fam.frame_times(10.0, 10.0).unwrap();
    assert_eq!(t, vec![1.2, 3.7, 6.2, 8.7]);
    let a = clip("landscape").render();
    let b = clip("portrait12").render();
    let p = fam.prepare(&[&a, &b]).unwrap();
    let view = fam.view(&p).unwrap();
    assert_eq!(view.visual_tokens, vec![27, 27]);
    let g = fam
        .generate(&p, &GenerateOptions::greedy(4, fam.eos_ids()), None)
        .unwrap();
    assert_eq!(g.tokens.len(), 2);
    // frames = N is Qwen3-VL's knob; here it is refused with the reason.
    let e = load_family(
        &WeightSource::local(fx.root.join("mistral-base")),
        &FamilyOptions {
            dtype: candle_core::DType::F32,
            device: candle_core::Device::Cpu,
            adapter: None,
            frames: Some(8),
            prompt: String::new(),
        },
    )
    .err()
    .unwrap();
    assert!(e.to_string().contains("num_frames = 4"), "{e}");
}

#[test]
fn broken_checkpoints_are_named_errors() {
    let fx = fixture();
    let dir = fx.root.join("mistral-base");
    let cfg_path = dir.join("config.json");
    let good: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&cfg_path).unwrap()).unwrap();
    let load_err = |cfg: serde_json::Value| -> ModelError {
        std::fs::write(&cfg_path, serde_json::to_string(&cfg).unwrap()).unwrap();
        VideoLlama2::load(&WeightSource::local(&dir), &LoadOptions::default())
            .err()
            .expect("refused")
    };
    let mut c = good.clone();
    c["mm_vision_tower"] = "/nowhere/clip-tower".into();
    let e = load_err(c).to_string();
    assert!(e.contains("/nowhere/clip-tower"), "{e}");
    let mut c = good.clone();
    c["mm_projector_type"] = "mlp2x_gelu".into();
    let e = load_err(c).to_string();
    assert!(e.contains("mlp2x_gelu"), "{e}");
    let mut c = good.clone();
    c["mm_vision_tower"] = "google/siglip-so400m-patch14-384".into();
    let e = load_err(c).to_string();
    assert!(e.contains("SigLIP"), "{e}");
    let mut c = good.clone();
    c["mm_hidden_size"] = 99.into();
    let e = load_err(c).to_string();
    assert!(e.contains("mm_hidden_size 99"), "{e}");
    let mut c = good.clone();
    c["model_type"] = "videollama2_qwen2".into();
    let e = load_err(c).to_string();
    assert!(e.contains("videollama2_qwen2"), "{e}");
    // A truncated shard names the file.
    std::fs::write(&cfg_path, serde_json::to_string(&good).unwrap()).unwrap();
    let st = dir.join("model.safetensors");
    let bytes = std::fs::read(&st).unwrap();
    std::fs::write(&st, &bytes[..bytes.len() / 2]).unwrap();
    let e = VideoLlama2::load(&WeightSource::local(&dir), &LoadOptions::default())
        .err()
        .unwrap()
        .to_string();
    assert!(e.contains("model.safetensors"), "{e}");
}
