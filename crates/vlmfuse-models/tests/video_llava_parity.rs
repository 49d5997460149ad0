//! VideoLLaVA against transformers 5.23 on the tiny fixture: preprocessing, input ids,
//! first-token logits, 16 greedy ids and the LoRA merge, compared with the reference outputs
//! `scripts/parity/video_llava.py` stored under `tests/data/parity/video_llava/`. The fixture is
//! rebuilt here by the same deterministic writer the script read.

use std::path::{Path, PathBuf};

use base64::Engine;
use candle_core::{DType, Device};
use vlmfuse_models::generate::{generate_with, GenerateOptions};
use vlmfuse_models::models::video_llava::transformers5_name;
use vlmfuse_models::models::video_llava::{
    KvCache, LoadOptions, ModelInputs, VideoLlava, VideoLlavaConfig, VideoLlavaProcessor,
};
use vlmfuse_models::{Frame, FrameRef, ModelError, WeightSource};
use vlmfuse_testkit_models::fixtures::video_llava::{SyntheticClip, PARITY_CLIPS};
use vlmfuse_testkit_models::fixtures::TinyVideoLlava;

/// Greedy ids of every row as transformers' `generate` returns them: up to `n` tokens, a stop
/// token included where a row met one.
fn greedy(
    model: &VideoLlava,
    inputs: &ModelInputs,
    n: usize,
    stop: &[u32],
    cache: &mut KvCache,
) -> Result<Vec<Vec<u32>>, ModelError> {
    let g = generate_with(
        model,
        inputs,
        cache,
        &GenerateOptions::greedy(n, stop),
        None,
    )?;
    Ok((0..g.tokens.len()).map(|r| g.with_stop(r)).collect())
}

const MODEL_SEED: u64 = 7;
const ADAPTER_SEED: u64 = 21;
const TOL: f32 = 1e-4;

fn data_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../tests/data/parity/video_llava")
}

fn read_json(name: &str) -> serde_json::Value {
    let p = data_dir().join(name);
    let text = std::fs::read_to_string(&p).unwrap_or_else(|e| {
        panic!(
            "{}: {e} (run scripts/parity/video_llava.py to create it)",
            p.display()
        )
    });
    serde_json::from_str(&text).unwrap()
}

fn b64(v: &serde_json::Value) -> Vec<u8> {
    base64::engine::general_purpose::STANDARD
        .decode(v.as_str().expect("base64 string"))
        .unwrap()
}

fn f32s(v: &serde_json::Value) -> Vec<f32> {
    b64(v)
        .chunks_exact(4)
        .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect()
}

fn ints(v: &serde_json::Value) -> Vec<Vec<u32>> {
    v.as_array()
        .unwrap()
        .iter()
        .map(|r| {
            r.as_array()
                .unwrap()
                .iter()
                .map(|x| x.as_u64().unwrap() as u32)
                .collect()
        })
        .collect()
}

struct Fixture {
    _tmp: tempfile::TempDir,
    model: PathBuf,
    adapter: PathBuf,
}

fn fixture() -> Fixture {
    let tmp = tempfile::tempdir().unwrap();
    let shape = TinyVideoLlava::default();
    let model = tmp.path().join("model");
    shape.write(&model, MODEL_SEED).unwrap();
    let adapter = tmp.path().join("adapter");
    shape
        .write_lora_adapter(&adapter, 4, 8.0, ADAPTER_SEED, Some(transformers5_name))
        .unwrap();
    Fixture {
        _tmp: tmp,
        model,
        adapter,
    }
}

fn load(dir: &Path, opts: LoadOptions) -> (VideoLlava, VideoLlavaProcessor) {
    let src = WeightSource::local(dir);
    let model = VideoLlava::load(&src, &opts).unwrap();
    let proc = VideoLlavaProcessor::load(&src, model.config()).unwrap();
    (model, proc)
}

fn opts() -> LoadOptions {
    LoadOptions {
        image_tower: true,
        ..LoadOptions::default()
    }
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

/// The case's inputs as the Rust processor builds them from the same clips and prompts.
fn inputs_for(proc: &VideoLlavaProcessor, case: &serde_json::Value) -> ModelInputs {
    let name = case["name"].as_str().unwrap();
    let prompts: Vec<String> = case["prompts"]
        .as_array()
        .unwrap()
        .iter()
        .map(|p| p.as_str().unwrap().to_string())
        .collect();
    if name == "text_only" {
        return proc.prepare_text(&[prompts[0].as_str()]).unwrap();
    }
    if let Some(img) = case.get("image").and_then(|i| i.as_str()) {
        let frames = clip(img).render();
        return proc.prepare_image(&prompts[0], frames[0].as_ref()).unwrap();
    }
    let clips: Vec<Vec<Frame>> = case["clips"]
        .as_array()
        .unwrap()
        .iter()
        .map(|c| clip(c.as_str().unwrap()).render())
        .collect();
    let texts: Vec<String> = prompts
        .iter()
        .map(|p| proc.video_prompt(prompt(p)))
        .collect();
    let frame_refs: Vec<Vec<FrameRef>> = clips.iter().map(|c| refs(c)).collect();
    let items: Vec<(&str, &[FrameRef])> = texts
        .iter()
        .zip(&frame_refs)
        .map(|(t, f)| (t.as_str(), f.as_slice()))
        .collect();
    proc.prepare_videos(&items).unwrap()
}

fn max_abs_diff(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len());
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max)
}

#[test]
fn preprocessing_matches_reference_to_the_grey_level() {
    let f = fixture();
    let (model, proc) = load(&f.model, opts());
    let pre = read_json("preprocess.json");
    let s = model.config().vision.image_size;
    for c in &PARITY_CLIPS {
        let want = &pre["clips"][c.name];
        let frames = c.render();
        let idx = VideoLlavaProcessor::sample_indices(frames.len(), proc.num_frames);
        let want_idx: Vec<usize> = want["indices"]
            .as_array()
            .unwrap()
            .iter()
            .map(|x| x.as_u64().unwrap() as usize)
            .collect();
        assert_eq!(idx, want_idx, "{}: sampled frames", c.name);

        // uint8 after resize + crop, first and last sampled frame, channel-first like the
        // reference: must be identical (the reference rounds to uint8 after each pass too).
        let ref_u8 = b64(&want["video_u8_first_last"]);
        let plane = 3 * s * s;
        for (k, &fi) in [idx[0], *idx.last().unwrap()].iter().enumerate() {
            let (img, w, h) = proc.video.resize_crop(frames[fi].as_ref()).unwrap();
            assert_eq!((w, h), (s, s));
            let chw: Vec<u8> = (0..3)
                .flat_map(|ch| (0..w * h).map(move |i| (i, ch)))
                .map(|(i, ch)| img[i * 3 + ch])
                .collect();
            let theirs = &ref_u8[k * plane..(k + 1) * plane];
            let off = chw.iter().zip(theirs).filter(|(a, b)| a != b).count();
            let worst = chw
                .iter()
                .zip(theirs)
                .map(|(a, b)| (*a as i32 - *b as i32).abs())
                .max()
                .unwrap();
            assert!(worst <= 1, "{} frame {fi}: {worst} grey levels off", c.name);
            assert_eq!(off, 0, "{} frame {fi}: {off} values off by one", c.name);
        }

        // Image processor (PIL arithmetic) on the clip's first frame.
        let px = proc.preprocess_image(frames[0].as_ref()).unwrap();
        let (img, w, h) = proc.image.resize_crop(frames[0].as_ref()).unwrap();
        assert_eq!((px.width, px.height), (w, h));
        let chw: Vec<u8> = (0..3)
            .flat_map(|ch| (0..w * h).map(move |i| (i, ch)))
            .map(|(i, ch)| img[i * 3 + ch])
            .collect();
        assert_eq!(chw, b64(&want["image_u8"]), "{}: image uint8", c.name);

        if let Some(f0) = want.get("video_frame0_f32") {
            let v = proc.preprocess_video(&refs(&frames)).unwrap();
            let d = max_abs_diff(&v.data[..plane], &f32s(f0));
            assert!(d <= 1e-6, "{}: normalised video frame off by {d}", c.name);
            let d = max_abs_diff(&px.data, &f32s(&want["image_f32"]));
            assert!(d <= 1e-6, "{}: normalised image off by {d}", c.name);
        }
    }
}

#[test]
fn input_ids_logits_and_greedy_ids_match_reference() {
    let f = fixture();
    let (model, proc) = load(&f.model, opts());
    let (lora, _) = load(
        &f.model,
        LoadOptions {
            adapter: Some(WeightSource::local(&f.adapter)),
            ..opts()
        },
    );
    let cases = read_json("cases.json");
    let mut report = Vec::new();
    for case in cases["cases"].as_array().unwrap() {
        let name = case["name"].as_str().unwrap();
        let m = if case["adapter"].as_bool().unwrap() {
            &lora
        } else {
            &model
        };
        let inputs = inputs_for(&proc, case);
        assert_eq!(
            inputs.ids.input_ids,
            ints(&case["input_ids"]),
            "{name}: input ids"
        );
        let mask: Vec<Vec<bool>> = ints(&case["attention_mask"])
            .into_iter()
            .map(|r| r.into_iter().map(|x| x == 1).collect())
            .collect();
        assert_eq!(inputs.ids.attention_mask, mask, "{name}: attention mask");

        let mut cache = m.new_cache(256);
        let logits = m.prefill(&inputs, &mut cache).unwrap();
        let got: Vec<f32> = logits.flatten_all().unwrap().to_vec1().unwrap();
        let want = f32s(&case["logits"]);
        let d = max_abs_diff(&got, &want);
        let range = want.iter().fold(f32::MIN, |a, &b| a.max(b))
            - want.iter().fold(f32::MAX, |a, &b| a.min(b));
        report.push(format!("{name}: max |Δlogit| {d:.2e} (range {range:.1})"));
        assert!(d <= TOL, "{name}: first-token logits differ by {d}");

        let ids = greedy(m, &inputs, 16, &[], &mut cache).unwrap();
        assert_eq!(ids, ints(&case["greedy"]), "{name}: greedy ids");
    }
    eprintln!("{}", report.join("\n"));
}

#[test]
fn lora_merge_touches_every_named_module_and_changes_the_output() {
    let f = fixture();
    let (base, proc) = load(&f.model, opts());
    let lora = VideoLlava::load(
        &WeightSource::local(&f.model),
        &LoadOptions {
            adapter: Some(WeightSource::local(&f.adapter)),
            ..opts()
        },
    )
    .unwrap();
    let shape = TinyVideoLlava::default();
    // q/v in every text layer and both towers' layers, plus the projector's linear_1.
    let want = 2 * shape.layers + 2 * 2 * shape.vision_layers + 1;
    assert_eq!(lora.merged_lora_keys().len(), want);
    assert!(lora
        .merged_lora_keys()
        .iter()
        .all(|k| k.starts_with("language_model.model.")
            || k.starts_with("video_tower.vision_model.")
            || k.starts_with("image_tower.vision_model.")
            || k.starts_with("multi_modal_projector.")));

    // An adapter under transformers 4 module names lands on the same weights.
    let tmp = tempfile::tempdir().unwrap();
    shape
        .write_lora_adapter(tmp.path(), 4, 8.0, ADAPTER_SEED, None)
        .unwrap();
    let legacy = VideoLlava::load(
        &WeightSource::local(&f.model),
        &LoadOptions {
            adapter: Some(WeightSource::local(tmp.path())),
            ..opts()
        },
    )
    .unwrap();
    let frames = clip("landscape").render();
    let text = proc.video_prompt(prompt("describe"));
    let fr = refs(&frames);
    let inputs = proc
        .prepare_videos(&[(text.as_str(), fr.as_slice())])
        .unwrap();
    let run = |m: &VideoLlava| -> Vec<f32> {
        let mut c = m.new_cache(256);
        m.prefill(&inputs, &mut c)
            .unwrap()
            .flatten_all()
            .unwrap()
            .to_vec1()
            .unwrap()
    };
    let (b, l, g) = (run(&base), run(&lora), run(&legacy));
    assert_eq!(l, g, "adapter naming changed the merge");
    assert!(max_abs_diff(&b, &l) > 1e-2, "the adapter changed nothing");
}

#[test]
fn one_pass_prefill_equals_token_by_token_decoding() {
    let f = fixture();
    let (model, proc) = load(&f.model, opts());
    let frames = clip("portrait12").render();
    let text = proc.video_prompt(prompt("manoeuvre"));
    let fr = refs(&frames);
    let inputs = proc
        .prepare_videos(&[(text.as_str(), fr.as_slice())])
        .unwrap();
    let mut cache = model.new_cache(256);
    let one = model.prefill(&inputs, &mut cache).unwrap();
    let steps = model.logits_token_by_token(&inputs, &mut cache).unwrap();
    let t = inputs.ids.seq_len();
    let last = steps.narrow(1, t - 1, 1).unwrap().squeeze(1).unwrap();
    let d = max_abs_diff(
        &one.flatten_all().unwrap().to_vec1().unwrap(),
        &last.flatten_all().unwrap().to_vec1().unwrap(),
    );
    assert!(d <= TOL, "chunked vs stepwise: {d}");
}

#[test]
fn batch_rows_equal_their_single_runs_even_with_different_frame_counts() {
    // transformers cannot stack clips of 8 and 5 frames; here each row is its own clip.
    let f = fixture();
    let (model, proc) = load(&f.model, opts());
    let a = clip("landscape").render();
    let b = clip("short5").render();
    let (ta, tb) = (
        proc.video_prompt(prompt("describe")),
        proc.video_prompt(prompt("manoeuvre")),
    );
    let (fa, fb) = (refs(&a), refs(&b));
    let batch = proc
        .prepare_videos(&[(ta.as_str(), fa.as_slice()), (tb.as_str(), fb.as_slice())])
        .unwrap();
    assert!(
        batch.ids.attention_mask[1].iter().any(|&v| !v),
        "row 1 is padded"
    );
    let mut cache = model.new_cache(512);
    let ids = greedy(&model, &batch, 8, &[], &mut cache).unwrap();
    let bl: Vec<f32> = model
        .prefill(&batch, &mut cache)
        .unwrap()
        .flatten_all()
        .unwrap()
        .to_vec1()
        .unwrap();
    for (r, (t, fr)) in [(ta.as_str(), &fa), (tb.as_str(), &fb)].iter().enumerate() {
        let single = proc.prepare_videos(&[(*t, fr.as_slice())]).unwrap();
        let mut c = model.new_cache(256);
        let sl: Vec<f32> = model
            .prefill(&single, &mut c)
            .unwrap()
            .flatten_all()
            .unwrap()
            .to_vec1()
            .unwrap();
        let v = sl.len();
        let d = max_abs_diff(&bl[r * v..(r + 1) * v], &sl);
        assert!(d <= TOL, "row {r}: batch vs single {d}");
        let sid = greedy(&model, &single, 8, &[], &mut c).unwrap();
        assert_eq!(ids[r], sid[0], "row {r} greedy ids");
    }
}

/// A checkpoint as transformers 5.23's `save_pretrained` writes it (from a model it built
/// itself: towers saved as `video_tower.*` without `vision_model`, the processors nested in
/// `processor_config.json`, no `preprocessor_config.json`), rebuilt from the fixture with the
/// names and files `scripts/parity/saved_layouts.py` recorded: it loads, and computes what the
/// hub layout computes.
#[test]
fn a_checkpoint_saved_by_transformers_5_23_loads_the_same_model() {
    let f = fixture();
    let saved = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../tests/data/parity/saved_5_23/video_llava");
    let read = |n: &str| -> serde_json::Value {
        serde_json::from_str(&std::fs::read_to_string(saved.join(n)).unwrap()).unwrap()
    };
    let (names, files) = (read("names.json"), read("files.json"));
    let tmp = tempfile::tempdir().unwrap();
    let tensors: std::collections::HashMap<String, candle_core::Tensor> = TinyVideoLlava::default()
        .tensors(MODEL_SEED)
        .into_iter()
        .map(|(k, v)| {
            (
                names[&k]
                    .as_str()
                    .unwrap_or_else(|| panic!("{k}"))
                    .to_string(),
                v,
            )
        })
        .collect();
    assert!(tensors
        .keys()
        .any(|k| k.starts_with("video_tower.embeddings.")));
    candle_core::safetensors::save(&tensors, tmp.path().join("model.safetensors")).unwrap();
    for (name, text) in files.as_object().unwrap() {
        std::fs::write(tmp.path().join(name), text.as_str().unwrap()).unwrap();
    }
    assert!(!tmp.path().join("preprocessor_config.json").exists());
    let (hub, hub_proc) = load(&f.model, opts());
    let (v523, proc) = load(tmp.path(), opts());
    let frames = clip("upscale").render();
    let fr = refs(&frames);
    let text = proc.video_prompt(prompt("describe"));
    let inputs = proc
        .prepare_videos(&[(text.as_str(), fr.as_slice())])
        .unwrap();
    let hub_inputs = hub_proc
        .prepare_videos(&[(
            hub_proc.video_prompt(prompt("describe")).as_str(),
            fr.as_slice(),
        )])
        .unwrap();
    let run = |m: &VideoLlava, i: &ModelInputs| -> Vec<f32> {
        let mut c = m.new_cache(256);
        m.prefill(i, &mut c)
            .unwrap()
            .flatten_all()
            .unwrap()
            .to_vec1()
            .unwrap()
    };
    assert_eq!(run(&hub, &hub_inputs), run(&v523, &inputs));
    // The LoRA adapter (transformers 5 module names) merges into either base alike.
    let with_adapter = || LoadOptions {
        adapter: Some(WeightSource::local(&f.adapter)),
        ..opts()
    };
    let (hub_l, _) = load(&f.model, with_adapter());
    let (v523_l, _) = load(tmp.path(), with_adapter());
    let merged = run(&v523_l, &inputs);
    assert_eq!(run(&hub_l, &hub_inputs), merged);
    assert_ne!(merged, run(&v523, &inputs), "the adapter changed nothing");
}

#[test]
fn transformers5_key_names_load_the_same_model() {
    let f = fixture();
    let tmp = tempfile::tempdir().unwrap();
    TinyVideoLlava::default()
        .write_transformers5_layout(tmp.path(), MODEL_SEED, transformers5_name)
        .unwrap();
    let (hub, proc) = load(&f.model, opts());
    let (v5, _) = load(tmp.path(), opts());
    let frames = clip("upscale").render();
    let text = proc.video_prompt(prompt("describe"));
    let fr = refs(&frames);
    let inputs = proc
        .prepare_videos(&[(text.as_str(), fr.as_slice())])
        .unwrap();
    let run = |m: &VideoLlava| -> Vec<f32> {
        let mut c = m.new_cache(256);
        m.prefill(&inputs, &mut c)
            .unwrap()
            .flatten_all()
            .unwrap()
            .to_vec1()
            .unwrap()
    };
    assert_eq!(run(&hub), run(&v5));
}

#[test]
fn one_model_serves_requests_one_after_another() {
    let f = fixture();
    let (model, proc) = load(&f.model, LoadOptions::default());
    let frames = clip("landscape").render();
    let text = proc.video_prompt(prompt("describe"));
    let fr = refs(&frames);
    let inputs = proc
        .prepare_videos(&[(text.as_str(), fr.as_slice())])
        .unwrap();
    let other = proc.prepare_text(&["USER: hi ASSISTANT:"]).unwrap();
    let mut cache = model.new_cache(64);
    let first = greedy(&model, &inputs, 6, &[], &mut cache).unwrap();
    greedy(&model, &other, 6, &[], &mut cache).unwrap();
    let again = greedy(&model, &inputs, 6, &[], &mut cache).unwrap();
    assert_eq!(first, again, "a previous request leaked into the next");
    // Stopping at EOS keeps the stop token and ends the row.
    let stop = [first[0][2]];
    let cut = greedy(&model, &inputs, 6, &stop, &mut cache).unwrap();
    assert_eq!(cut[0], first[0][..3].to_vec());
}

#[test]
fn half_precision_runs_and_agrees_on_the_first_token() {
    let f = fixture();
    let (m32, proc) = load(&f.model, LoadOptions::default());
    let frames = clip("landscape").render();
    let text = proc.video_prompt(prompt("describe"));
    let fr = refs(&frames);
    let inputs = proc
        .prepare_videos(&[(text.as_str(), fr.as_slice())])
        .unwrap();
    let mut c = m32.new_cache(256);
    let l32: Vec<f32> = m32
        .prefill(&inputs, &mut c)
        .unwrap()
        .flatten_all()
        .unwrap()
        .to_vec1()
        .unwrap();
    for dtype in [DType::BF16, DType::F16] {
        let m = VideoLlava::load(
            &WeightSource::local(&f.model),
            &LoadOptions {
                dtype,
                device: Device::Cpu,
                ..LoadOptions::default()
            },
        )
        .unwrap();
        let mut c = m.new_cache(256);
        let l: Vec<f32> = m
            .prefill(&inputs, &mut c)
            .unwrap()
            .flatten_all()
            .unwrap()
            .to_vec1()
            .unwrap();
        let am = |v: &[f32]| {
            v.iter()
                .enumerate()
                .max_by(|a, b| a.1.total_cmp(b.1))
                .unwrap()
                .0
        };
        assert_eq!(am(&l), am(&l32), "{dtype:?} first token");
        let d = max_abs_diff(&l, &l32);
        assert!(d < 1.0, "{dtype:?} drifts by {d}");
    }
}

#[test]
fn bad_inputs_are_errors_not_panics() {
    let f = fixture();
    let (model, proc) = load(&f.model, LoadOptions::default());
    let frames = clip("landscape").render();
    let fr = refs(&frames);
    // Placeholders and clips must match.
    let e = proc
        .prepare_videos(&[("USER: no placeholder ASSISTANT:", fr.as_slice())])
        .unwrap_err();
    assert_eq!(e.kind(), "invalid_input", "{e}");
    let two = "USER: <video><video> ASSISTANT:";
    assert!(proc.prepare_videos(&[(two, fr.as_slice())]).is_err());
    // No frames; a torn frame buffer.
    let text = proc.video_prompt("x");
    assert!(proc.prepare_videos(&[(text.as_str(), &[])]).is_err());
    let torn = FrameRef {
        width: 10,
        height: 10,
        rgb: &[0u8; 10],
    };
    let e = proc
        .prepare_videos(&[(text.as_str(), &[torn])])
        .unwrap_err();
    assert!(e.to_string().contains("RGB bytes"), "{e}");
    // Frames of different sizes are fine as long as the crop makes them one size (it always
    // does with a crop size, as in the reference).
    let other = clip("short5").render();
    let mixed = [fr[0], other[0].as_ref()];
    assert!(proc.prepare_videos(&[(text.as_str(), &mixed)]).is_ok());
    // An image prompt to a model loaded without the image tower.
    let img = proc.prepare_image(&proc.image_prompt("x"), fr[0]).unwrap();
    let mut c = model.new_cache(64);
    let e = model.prefill(&img, &mut c).unwrap_err();
    assert!(e.to_string().contains("image tower"), "{e}");
    // Ids outside the vocabulary, step before prefill, wrong batch.
    let mut bad = proc.prepare_text(&["USER: hi ASSISTANT:"]).unwrap();
    bad.ids.input_ids[0][1] = 1_000_000;
    assert!(model.prefill(&bad, &mut c).is_err());
    let mut fresh = model.new_cache(8);
    assert!(model.step(&[1], &mut fresh).is_err());
    let ok = proc.prepare_text(&["USER: hi ASSISTANT:"]).unwrap();
    model.prefill(&ok, &mut c).unwrap();
    assert!(model.step(&[1, 2], &mut c).is_err());
}

#[test]
fn broken_checkpoints_are_named_errors() {
    let f = fixture();
    // Wrong architecture.
    let tmp = tempfile::tempdir().unwrap();
    TinyVideoLlava::default()
        .write(tmp.path(), MODEL_SEED)
        .unwrap();
    let p = tmp.path().join("config.json");
    let mut cfg: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&p).unwrap()).unwrap();
    cfg["model_type"] = "llava".into();
    std::fs::write(&p, cfg.to_string()).unwrap();
    let e = VideoLlava::load(&WeightSource::local(tmp.path()), &LoadOptions::default())
        .err()
        .unwrap();
    assert!(e.to_string().contains("llava"), "{e}");
    // Weights that do not fit the config (a wider hidden size).
    cfg["model_type"] = "video_llava".into();
    cfg["text_config"]["hidden_size"] = 128.into();
    std::fs::write(&p, cfg.to_string()).unwrap();
    let e = VideoLlava::load(&WeightSource::local(tmp.path()), &LoadOptions::default())
        .err()
        .unwrap();
    assert_eq!(e.kind(), "bad_weights", "{e}");
    // An adapter naming a module the model lacks.
    let ad = tempfile::tempdir().unwrap();
    TinyVideoLlava {
        layers: 3,
        ..TinyVideoLlava::default()
    }
    .write_lora_adapter(ad.path(), 2, 4.0, 1, Some(transformers5_name))
    .unwrap();
    let e = VideoLlava::load(
        &WeightSource::local(&f.model),
        &LoadOptions {
            adapter: Some(WeightSource::local(ad.path())),
            ..LoadOptions::default()
        },
    )
    .err()
    .unwrap();
    assert!(e.to_string().contains("layers.2"), "{e}");
    // A tokenizer whose <video> id disagrees with config.json.
    let src = WeightSource::local(&f.model);
    let mut c = VideoLlavaConfig::from_json(&src.read_json("config.json").unwrap()).unwrap();
    c.video_token_id += 1;
    let e = VideoLlavaProcessor::load(&src, &c).err().unwrap();
    assert!(matches!(e, ModelError::BadConfig(_)), "{e}");
}
