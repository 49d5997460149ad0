//! Qwen3-VL against transformers: the reference outputs under `tests/data/parity/qwen3_vl/`
//! were computed by `scripts/parity/qwen3_vl.py` with transformers' own model and processor on
//! the same fixture (`TinyQwen3Vl::default()`, seed 7, f32). Targets: first-token and 16th-token
//! logits within 1e-4, greedy ids identical, pixels within one grey level, prompt text and ids
//! identical.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use base64::Engine as _;
use candle_core::DType;
use serde_json::Value;
use vlmfuse_models::generate::argmax_rows;
use vlmfuse_models::models::qwen3_vl::{
    Cache, LoadOptions, Qwen3Vl, Qwen3VlProcessor, Sequence, VideoProcessor, VideoProcessorConfig,
};
use vlmfuse_models::{FrameRef, ModelError, WeightSource};
use vlmfuse_testkit_models::fixtures::qwen3_vl::parity_frame;
use vlmfuse_testkit_models::fixtures::TinyQwen3Vl;

const LOGIT_TOL: f32 = 1e-4;

fn data_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../tests/data/parity/qwen3_vl")
}

fn read(name: &str) -> Value {
    let p = data_dir().join(name);
    let text = std::fs::read_to_string(&p)
        .unwrap_or_else(|e| panic!("{}: {e} (run scripts/parity/qwen3_vl.py)", p.display()));
    serde_json::from_str(&text).unwrap()
}

/// The synthetic clip of the reference script (same integer formula).
fn frames(n: usize, w: usize, h: usize, k0: usize) -> Vec<Vec<u8>> {
    (k0..k0 + n).map(|k| parity_frame(w, h, k)).collect()
}

fn refs(frames: &[Vec<u8>], w: usize, h: usize) -> Vec<FrameRef<'_>> {
    frames
        .iter()
        .map(|rgb| FrameRef {
            width: w as u32,
            height: h as u32,
            rgb,
        })
        .collect()
}

fn u(v: &Value, k: &str) -> usize {
    v[k].as_u64().unwrap_or_else(|| panic!("{k} in {v}")) as usize
}

fn floats(v: &Value) -> Vec<f32> {
    v.as_array()
        .unwrap()
        .iter()
        .map(|x| x.as_f64().unwrap() as f32)
        .collect()
}

fn ids(v: &Value) -> Vec<u32> {
    v.as_array()
        .unwrap()
        .iter()
        .map(|x| x.as_u64().unwrap() as u32)
        .collect()
}

/// Normalised pixels (mean and std 0.5) against the reference's grey levels: the largest
/// difference in grey levels and how many values differ at all.
fn grey_level_diff(want: &[u8], pixels: &[f32]) -> (f32, usize) {
    let mut worst = 0f32;
    let mut off = 0usize;
    for (&g, &x) in want.iter().zip(pixels) {
        let d = (x * 127.5 + 127.5 - g as f32).abs();
        worst = worst.max(d);
        off += (d > 1e-3) as usize;
    }
    (worst, off)
}

fn max_abs_diff(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len());
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max)
}

struct Fixture {
    _dir: tempfile::TempDir,
    src: WeightSource,
    model: Qwen3Vl,
    proc: Qwen3VlProcessor,
}

/// Writes the fixture, checks it is the one the references were made from, loads it in f32.
fn fixture() -> Fixture {
    let dir = tempfile::tempdir().unwrap();
    let tiny = TinyQwen3Vl::default();
    tiny.write(dir.path(), 7).unwrap();
    let meta = &read("reference.json")["meta"];
    let (vis, txt) = tiny.tensors(7);
    let sums = meta["fixture"]["tensor_sums"].as_object().unwrap();
    assert_eq!(
        sums.len(),
        vis.len() + txt.len(),
        "fixture tensor set changed"
    );
    for (k, t) in vis.iter().chain(txt.iter()) {
        let ours = t
            .to_dtype(DType::F64)
            .unwrap()
            .sum_all()
            .unwrap()
            .to_scalar::<f64>()
            .unwrap();
        let theirs = sums[k]
            .as_f64()
            .unwrap_or_else(|| panic!("reference lacks {k}"));
        assert!(
            (ours - theirs).abs() <= 1e-4 * (1.0 + theirs.abs()),
            "fixture tensor {k} changed ({ours} vs {theirs}): rerun scripts/parity/qwen3_vl.py"
        );
    }
    let src = WeightSource::local(dir.path());
    let model = Qwen3Vl::load(&src, &LoadOptions::default()).unwrap();
    let proc = Qwen3VlProcessor::load(&src, model.config()).unwrap();
    Fixture {
        _dir: dir,
        src,
        model,
        proc,
    }
}

/// A reference case as the engine builds it: frames → processor → sequence.
fn sequence(f: &Fixture, case: &Value) -> Sequence {
    let prompt = case["prompt"].as_str().unwrap();
    let n = u(case, "frames");
    let seq = if n == 0 {
        f.proc.prepare(prompt, None).unwrap()
    } else {
        let (w, h) = (u(case, "width"), u(case, "height"));
        let clip = frames(n, w, h, u(case, "k0"));
        let fps = case["video_fps"].as_f64().unwrap();
        let times: Vec<f64> = ids(&case["indices"])
            .iter()
            .map(|&i| i as f64 / fps)
            .collect();
        let v = f.proc.video.process(&refs(&clip, w, h), &times).unwrap();
        assert_eq!(
            f.proc.prompt_text(prompt, Some(&v)),
            case["prompt_text"].as_str().unwrap(),
            "{}: prompt text",
            case["name"]
        );
        f.proc.prepare(prompt, Some(v)).unwrap()
    };
    assert_eq!(
        seq.ids,
        ids(&case["input_ids"]),
        "{}: input ids",
        case["name"]
    );
    if let Some(v) = &seq.video {
        let grid: Vec<usize> = ids(&case["video_grid_thw"])
            .into_iter()
            .map(|x| x as usize)
            .collect();
        assert_eq!(v.grid_thw.to_vec(), grid, "{}: grid", case["name"]);
        let sum: f64 = v.pixel_values.iter().map(|&x| x as f64).sum();
        let want = case["pixel_sum"].as_f64().unwrap();
        assert!(
            (sum - want).abs() < 1e-2,
            "{}: pixel sum {sum} vs {want}",
            case["name"]
        );
    }
    seq
}

/// Greedy decoding that keeps each step's logits: `(ids, logits that chose the last id)`.
fn greedy_with_logits(
    model: &Qwen3Vl,
    batch: &[Sequence],
    n: usize,
) -> (Vec<Vec<u32>>, Vec<Vec<f32>>) {
    let mut cache = Cache::new(512);
    let mut logits = model.prefill(batch, &mut cache).unwrap();
    let mut out = vec![Vec::new(); batch.len()];
    for i in 0..n {
        let next = argmax_rows(&logits).unwrap();
        for (r, &t) in next.iter().enumerate() {
            out[r].push(t);
        }
        if i + 1 < n {
            logits = model.step(&next, &mut cache).unwrap();
        }
    }
    (out, logits.to_vec2::<f32>().unwrap())
}

#[test]
fn logits_and_greedy_ids_match_transformers() {
    let f = fixture();
    let reference = read("reference.json");
    let mut report = Vec::new();
    for case in reference["cases"].as_array().unwrap() {
        let name = case["name"].as_str().unwrap();
        let seq = sequence(&f, case);
        let mut cache = Cache::new(64);
        let first = f
            .model
            .prefill(std::slice::from_ref(&seq), &mut cache)
            .unwrap()
            .to_vec2::<f32>()
            .unwrap()
            .remove(0);
        let d_first = max_abs_diff(&first, &floats(&case["first_logits"]));
        let (greedy, last) = greedy_with_logits(&f.model, std::slice::from_ref(&seq), 16);
        let d_last = max_abs_diff(&last[0], &floats(&case["greedy_last_logits"]));
        report.push(format!(
            "{name}: {} tokens, first-token max|d| {d_first:.2e}, 16th-token max|d| {d_last:.2e}",
            seq.ids.len()
        ));
        assert!(
            d_first <= LOGIT_TOL,
            "{name}: first-token logits differ by {d_first}"
        );
        assert_eq!(greedy[0], ids(&case["greedy_ids"]), "{name}: greedy ids");
        assert!(
            d_last <= LOGIT_TOL,
            "{name}: 16th-token logits differ by {d_last}"
        );
    }
    eprintln!("{}", report.join("\n"));
}

#[test]
fn padded_batch_matches_transformers_and_the_rows_alone() {
    let f = fixture();
    let reference = read("reference.json");
    let by_name: HashMap<&str, &Value> = reference["cases"]
        .as_array()
        .unwrap()
        .iter()
        .map(|c| (c["name"].as_str().unwrap(), c))
        .collect();
    let b = &reference["batch"];
    let rows: Vec<&str> = b["rows"]
        .as_array()
        .unwrap()
        .iter()
        .map(|r| r.as_str().unwrap())
        .collect();
    let batch: Vec<Sequence> = rows.iter().map(|r| sequence(&f, by_name[r])).collect();
    let mut cache = Cache::new(320);
    let first = f
        .model
        .prefill(&batch, &mut cache)
        .unwrap()
        .to_vec2::<f32>()
        .unwrap();
    let pads: Vec<usize> = ids(&b["padding"]).into_iter().map(|p| p as usize).collect();
    assert_eq!(cache.padding(), pads.as_slice(), "left padding");
    let want_first: Vec<Vec<f32>> = b["first_logits"]
        .as_array()
        .unwrap()
        .iter()
        .map(floats)
        .collect();
    let (greedy, last) = greedy_with_logits(&f.model, &batch, 16);
    let want_last: Vec<Vec<f32>> = b["greedy_last_logits"]
        .as_array()
        .unwrap()
        .iter()
        .map(floats)
        .collect();
    for (i, name) in rows.iter().enumerate() {
        let d = max_abs_diff(&first[i], &want_first[i]);
        let alone = max_abs_diff(&first[i], &floats(&by_name[name]["first_logits"]));
        let dl = max_abs_diff(&last[i], &want_last[i]);
        eprintln!("batch row {name}: vs batched reference {d:.2e}, vs reference alone {alone:.2e}, 16th {dl:.2e}");
        assert!(
            d <= LOGIT_TOL && alone <= LOGIT_TOL && dl <= LOGIT_TOL,
            "{name}: {d} {alone} {dl}"
        );
        assert_eq!(
            greedy[i],
            ids(&b["greedy_ids"][i]),
            "{name}: batched greedy ids"
        );
    }
}

#[test]
fn preprocessing_matches_the_video_processor() {
    let f = fixture();
    let p = read("preprocessing.json");
    let base: Value = serde_json::from_str(
        &std::fs::read_to_string(f.src.resolve("video_preprocessor_config.json").unwrap()).unwrap(),
    )
    .unwrap();
    for case in p["cases"].as_array().unwrap() {
        let name = case["name"].as_str().unwrap();
        let mut cfg = base.clone();
        for (k, v) in case["overrides"].as_object().unwrap() {
            cfg[k] = v.clone();
        }
        let vcfg = VideoProcessorConfig::from_json(&cfg, name).unwrap();
        let proc =
            Qwen3VlProcessor::new(f.proc.tokenizer().clone(), vcfg.clone(), f.model.config())
                .unwrap();
        let (w, h) = (u(case, "width"), u(case, "height"));
        let clip = frames(u(case, "frames"), w, h, u(case, "k0"));
        let fps = case["video_fps"].as_f64().unwrap();
        let times: Vec<f64> = ids(&case["indices"])
            .iter()
            .map(|&i| i as f64 / fps)
            .collect();
        let v = proc.video.process(&refs(&clip, w, h), &times).unwrap();
        let resized: Vec<usize> = ids(&case["resized"])
            .into_iter()
            .map(|x| x as usize)
            .collect();
        assert_eq!(
            vec![v.resized.0, v.resized.1],
            resized,
            "{name}: resized size"
        );
        let grid: Vec<usize> = ids(&case["video_grid_thw"])
            .into_iter()
            .map(|x| x as usize)
            .collect();
        assert_eq!(v.input.grid_thw.to_vec(), grid, "{name}: grid");
        let want = base64::engine::general_purpose::STANDARD
            .decode(case["pixel_grey_b64"].as_str().unwrap())
            .unwrap();
        assert_eq!(
            want.len(),
            v.input.pixel_values.len(),
            "{name}: pixel count"
        );
        let (worst, off) = grey_level_diff(&want, &v.input.pixel_values);
        eprintln!(
            "{name}: {}x{} -> {}x{}, grid {:?}, max |grey level diff| {worst:.4}, {off} of {} values off",
            w, h, v.resized.1, v.resized.0, v.input.grid_thw, want.len()
        );
        assert!(
            worst <= 1.0 + 1e-3,
            "{name}: pixels off by {worst} grey levels"
        );
        let prompt = case["prompt"].as_str().unwrap();
        assert_eq!(
            proc.prompt_text(prompt, Some(&v)),
            case["prompt_text"].as_str().unwrap(),
            "{name}: prompt"
        );
        let seq = proc.prepare(prompt, Some(v)).unwrap();
        assert_eq!(seq.ids, ids(&case["input_ids"]), "{name}: ids");
    }
    let vp = VideoProcessor::new(VideoProcessorConfig::from_json(&base, "fixture").unwrap());
    for s in p["sampling"].as_array().unwrap() {
        let got = vp.sample_indices(u(s, "total"), s["video_fps"].as_f64().unwrap());
        let want: Vec<usize> = ids(&s["indices"]).into_iter().map(|x| x as usize).collect();
        assert_eq!(got, want, "sampling {s}");
    }
}

/// The fixture's processor config states what the engine does, and transformers read it back
/// with the same semantics (the reference script stores its parsed view).
#[test]
fn fixture_processor_config_is_what_transformers_read() {
    let f = fixture();
    let theirs = &read("preprocessing.json")["video_processor"];
    let ours = &f.proc.video.config;
    assert_eq!(u(&theirs["size"], "shortest_edge"), ours.min_pixels);
    assert_eq!(u(&theirs["size"], "longest_edge"), ours.max_pixels);
    assert_eq!(theirs["fps"].as_f64().unwrap(), ours.fps);
    for (k, v) in [
        ("patch_size", ours.patch_size),
        ("temporal_patch_size", ours.temporal_patch_size),
        ("merge_size", ours.merge_size),
        ("min_frames", ours.min_frames),
        ("max_frames", ours.max_frames),
    ] {
        assert_eq!(u(theirs, k), v, "{k}");
    }
    assert_eq!(
        theirs["cap_pixels_per_frame"].as_bool(),
        Some(ours.cap_pixels_per_frame)
    );
}

/// A prompt fed in one pass equals the same prompt fed as a chunk then token by token: the
/// causal mask inside a multi-token chunk and the KV cache agree.
#[test]
fn one_pass_prefill_equals_incremental_feeding() {
    let f = fixture();
    let reference = read("reference.json");
    for case in reference["cases"].as_array().unwrap() {
        let seq = sequence(&f, case);
        let mut cache = Cache::new(8);
        let full = f
            .model
            .prefill(std::slice::from_ref(&seq), &mut cache)
            .unwrap();
        assert_eq!(cache.len(), seq.ids.len());
        let n = seq.ids.len();
        let head = Sequence {
            ids: seq.ids[..n - 3].to_vec(),
            video: seq.video.clone(),
        };
        let mut cache = Cache::new(8); // grows past its reservation
        f.model.prefill(&[head], &mut cache).unwrap();
        let mut last = None;
        for &t in &seq.ids[n - 3..] {
            last = Some(f.model.step(&[t], &mut cache).unwrap());
        }
        let d = max_abs_diff(
            &full.to_vec2::<f32>().unwrap()[0],
            &last.unwrap().to_vec2::<f32>().unwrap()[0],
        );
        assert!(d < 1e-4, "{}: incremental differs by {d}", case["name"]);
    }
}

#[test]
fn half_precision_runs_and_stays_close() {
    let f = fixture();
    let reference = read("reference.json");
    let case = &reference["cases"][0];
    let seq = sequence(&f, case);
    let want = floats(&case["first_logits"]);
    let range = case["logit_range"].as_f64().unwrap() as f32;
    for dtype in [DType::BF16, DType::F16] {
        let m = Qwen3Vl::load(
            &f.src,
            &LoadOptions {
                dtype,
                ..Default::default()
            },
        )
        .unwrap();
        let got = m
            .prefill(std::slice::from_ref(&seq), &mut Cache::new(8))
            .unwrap()
            .to_vec2::<f32>()
            .unwrap()
            .remove(0);
        let d = max_abs_diff(&got, &want);
        eprintln!(
            "{dtype:?}: max|d| {d:.3} ({:.1}% of the range)",
            100.0 * d / range
        );
        assert!(d < 0.05 * range, "{dtype:?} drifted by {d}");
    }
}

#[test]
fn lora_is_merged_at_load() {
    let f = fixture();
    let tiny = TinyQwen3Vl::default();
    let adir = tempfile::tempdir().unwrap();
    tiny.write_lora_adapter(adir.path(), 4, 8.0, 11).unwrap();
    let m = Qwen3Vl::load(
        &f.src,
        &LoadOptions {
            adapter: Some(WeightSource::local(adir.path())),
            ..Default::default()
        },
    )
    .unwrap();
    assert_eq!(m.merged_lora_keys().len(), 2 * tiny.layers);
    let seq = f.proc.prepare("describe the road", None).unwrap();
    let a = f
        .model
        .prefill(std::slice::from_ref(&seq), &mut Cache::new(8))
        .unwrap();
    let b = m
        .prefill(std::slice::from_ref(&seq), &mut Cache::new(8))
        .unwrap();
    let d = max_abs_diff(
        &a.to_vec2::<f32>().unwrap()[0],
        &b.to_vec2::<f32>().unwrap()[0],
    );
    assert!(d > 1e-3, "adapter changed nothing ({d})");
}

#[test]
fn malformed_requests_are_clear_errors() {
    let f = fixture();
    let mut cache = Cache::new(8);
    let e = f.model.step(&[1], &mut cache).unwrap_err();
    assert!(
        matches!(e, ModelError::InvalidInput(_)) && e.to_string().contains("before prefill"),
        "{e}"
    );
    assert!(f.model.prefill(&[], &mut cache).is_err());
    let vid = f.model.config().video_token_id;
    let e = f
        .model
        .prefill(
            &[Sequence {
                ids: vec![2, vid, vid],
                video: None,
            }],
            &mut cache,
        )
        .unwrap_err();
    assert!(e.to_string().contains("no video"), "{e}");
    let e = f
        .model
        .prefill(
            &[Sequence {
                ids: vec![2, 9999],
                video: None,
            }],
            &mut cache,
        )
        .unwrap_err();
    assert!(e.to_string().contains("vocabulary"), "{e}");
    let clip = frames(2, 64, 64, 0);
    let mut seq = f
        .proc
        .prepare_frames("describe", &refs(&clip, 64, 64), &[0.0, 0.5])
        .unwrap();
    let last = seq.ids.iter().rposition(|&t| t == vid).unwrap();
    seq.ids.remove(last);
    let e = f.model.prefill(&[seq], &mut cache).unwrap_err();
    assert!(e.to_string().contains("placeholders"), "{e}");
    let seq = f.proc.prepare("describe", None).unwrap();
    f.model.prefill(&[seq.clone(), seq], &mut cache).unwrap();
    let e = f.model.step(&[1], &mut cache).unwrap_err();
    assert!(e.to_string().contains("batch of 2"), "{e}");
    // Frames of different sizes in one clip.
    let a = frames(1, 8, 8, 0);
    let b = frames(1, 16, 8, 0);
    let e = f
        .proc
        .video
        .process(&[refs(&a, 8, 8)[0], refs(&b, 16, 8)[0]], &[0.0, 1.0])
        .unwrap_err();
    assert!(e.to_string().contains("share a size"), "{e}");
}

fn saved_dir(sub: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../tests/data/parity/saved_5_23")
        .join(sub)
}

/// Writes the text files `save_pretrained` wrote (recorded by scripts/parity/saved_layouts.py)
/// into `dir`, and removes the older layout's separate processor files. The tokenizer files are
/// left as the fixture wrote them: transformers turns the fixture's hand-built word-level
/// vocabulary into a `Qwen2Tokenizer` BPE when it saves it, a change of tokenizer, not of layout
/// (tokenization is compared with transformers by the tests above).
fn write_saved_files(dir: &Path, sub: &str) {
    let files: Value =
        serde_json::from_str(&std::fs::read_to_string(saved_dir(sub).join("files.json")).unwrap())
            .unwrap();
    for old in ["preprocessor_config.json", "video_preprocessor_config.json"] {
        let _ = std::fs::remove_file(dir.join(old));
    }
    for (name, text) in files.as_object().unwrap() {
        if name.starts_with("tokenizer") {
            continue;
        }
        std::fs::write(dir.join(name), text.as_str().unwrap()).unwrap();
    }
    assert!(!dir.join("video_preprocessor_config.json").exists());
}

/// The fixture as transformers 5.23's `save_pretrained` writes it (the video processor nested in
/// `processor_config.json`, no separate processor files): it loads with the same processor
/// settings as the older layout and gives transformers' logits and greedy ids.
#[test]
fn a_checkpoint_saved_by_transformers_5_23_loads_and_matches() {
    let old = fixture();
    let dir = tempfile::tempdir().unwrap();
    TinyQwen3Vl::default().write(dir.path(), 7).unwrap();
    let names: Value = serde_json::from_str(
        &std::fs::read_to_string(saved_dir("qwen3_vl").join("names.json")).unwrap(),
    )
    .unwrap();
    let (vis, txt) = TinyQwen3Vl::default().tensors(7);
    assert!(
        vis.keys().chain(txt.keys()).all(|k| names[k] == *k),
        "5.23 renames Qwen3-VL tensors: rebuild model.safetensors with names.json"
    );
    write_saved_files(dir.path(), "qwen3_vl");
    let src = WeightSource::local(dir.path());
    let model = Qwen3Vl::load(&src, &LoadOptions::default()).unwrap();
    let proc = Qwen3VlProcessor::load(&src, model.config()).unwrap();
    assert_eq!(proc.video.config, old.proc.video.config);
    let f = Fixture {
        _dir: dir,
        src,
        model,
        proc,
    };
    let reference = read("reference.json");
    let case = reference["cases"]
        .as_array()
        .unwrap()
        .iter()
        .find(|c| c["name"] == "video8_describe")
        .unwrap();
    let seq = sequence(&f, case);
    let (greedy, _) = greedy_with_logits(&f.model, std::slice::from_ref(&seq), 16);
    assert_eq!(greedy[0], ids(&case["greedy_ids"]));
}

/// The released checkpoints' video processor (patch 16, their pixel budget and mean/std) as
/// transformers 5.23 saves it, nested in `processor_config.json`: read as transformers reads
/// it (the recorded settings), and the same grid and grey levels as transformers on a clip.
/// Before, the nested settings were not read and the class defaults gave another budget. The
/// same settings in the older layout (`video_preprocessor_config.json`) read the same.
#[test]
fn a_nested_patch16_processor_reads_and_runs_as_transformers() {
    let reference: Value = serde_json::from_str(
        &std::fs::read_to_string(saved_dir("qwen3_vl_patch16").join("reference.json")).unwrap(),
    )
    .unwrap();
    let dir = tempfile::tempdir().unwrap();
    write_saved_files(dir.path(), "qwen3_vl_patch16");
    let nested = VideoProcessorConfig::from_source(&WeightSource::local(dir.path())).unwrap();
    let set = &reference["settings"];
    assert_eq!(nested.patch_size, u(set, "patch_size"));
    assert_eq!(nested.min_pixels, u(&set["size"], "shortest_edge"));
    assert_eq!(nested.max_pixels, u(&set["size"], "longest_edge"));
    assert_eq!(nested.min_frames, u(set, "min_frames"));
    assert_eq!(nested.max_frames, u(set, "max_frames"));
    assert_eq!(nested.fps, set["fps"].as_f64().unwrap());
    assert_eq!(nested.image_mean.to_vec(), floats(&set["image_mean"]));
    assert_eq!(nested.image_std.to_vec(), floats(&set["image_std"]));
    // The older layout: the same settings in their own file.
    let files: Value = serde_json::from_str(
        &std::fs::read_to_string(saved_dir("qwen3_vl_patch16").join("files.json")).unwrap(),
    )
    .unwrap();
    let proc_cfg: Value =
        serde_json::from_str(files["processor_config.json"].as_str().unwrap()).unwrap();
    let old = tempfile::tempdir().unwrap();
    std::fs::write(
        old.path().join("video_preprocessor_config.json"),
        proc_cfg["video_processor"].to_string(),
    )
    .unwrap();
    let separate = VideoProcessorConfig::from_source(&WeightSource::local(old.path())).unwrap();
    assert_eq!(separate, nested);

    let fr = &reference["frames"];
    let (n, w, h) = (u(fr, "n"), u(fr, "width"), u(fr, "height"));
    let clip = frames(n, w, h, u(fr, "k0"));
    let times: Vec<f64> = (0..n).map(|i| i as f64 / 2.0).collect();
    let v = VideoProcessor::new(nested)
        .process(&refs(&clip, w, h), &times)
        .unwrap();
    let grid: Vec<usize> = ids(&reference["grid_thw"])
        .into_iter()
        .map(|x| x as usize)
        .collect();
    assert_eq!(v.input.grid_thw.to_vec(), grid, "grid");
    let want = base64::engine::general_purpose::STANDARD
        .decode(reference["grey_u8"].as_str().unwrap())
        .unwrap();
    assert_eq!(want.len(), v.input.pixel_values.len());
    let (worst, _) = grey_level_diff(&want, &v.input.pixel_values);
    assert!(worst <= 1.0 + 1e-3, "pixels off by {worst} grey levels");
}
