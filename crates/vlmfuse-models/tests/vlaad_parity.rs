//! VLAAD against the sungyeonparkk/vision-assistant-for-driving repository's own code
//! (Video-LLaMA's layout, transformers 4.28) on the tiny release: the frames its `load_video`
//! decodes (decord, scaled while decoding) against the service's decoder, the prompt and its
//! tokens, the clip's 4 LLaMA tokens out of ViT + Q-Former + video Q-Former, first-token
//! logits, 16 greedy ids, and a LoRA adapter (`adapter_model.bin`) on the LLaMA, compared with
//! the outputs `scripts/parity/vlaad.py` stored under `tests/data/parity/vlaad/`.

use std::path::PathBuf;

use vlmfuse_models::generate::{generate_with, GenerateOptions};
use vlmfuse_models::models::family::{load_family, FamilyOptions};
use vlmfuse_models::models::vlaad::family::load_tokenizer;
use vlmfuse_models::models::vlaad::{
    LoadOptions, ModelInputs, Vlaad, VlaadProcessor, VISUAL_TOKEN,
};
use vlmfuse_models::{FrameRef, ModelError, WeightSource};
use vlmfuse_testkit_models::fixtures::TinyVlaad;
use vlmfuse_testkit_models::parity::{b64, f32s, max_abs_diff};

const MODEL_SEED: u64 = 9;
const ADAPTER_SEED: u64 = 29;
const TOL: f32 = 1e-4;

fn data(name: &str) -> PathBuf {
    vlmfuse_testkit_models::parity::data_dir("vlaad").join(name)
}

fn cases() -> Vec<serde_json::Value> {
    let v = vlmfuse_testkit_models::parity::read_reference(
        "vlaad",
        "cases.json",
        "scripts/parity/vlaad.py",
    );
    v["cases"].as_array().unwrap().clone()
}

struct Fixture {
    _tmp: tempfile::TempDir,
    release: PathBuf,
    lora: PathBuf,
}

fn fixture() -> Fixture {
    let tmp = tempfile::tempdir().unwrap();
    let t = TinyVlaad::default();
    let release = tmp.path().join("release");
    t.write(&release, MODEL_SEED).unwrap();
    let lora = tmp.path().join("lora");
    t.write_lora_adapter(&lora, 4, 8.0, ADAPTER_SEED).unwrap();
    Fixture {
        _tmp: tmp,
        release,
        lora,
    }
}

fn load(fx: &Fixture, lora: bool) -> (Vlaad, VlaadProcessor) {
    let model = Vlaad::load(
        &WeightSource::local(&fx.release),
        &LoadOptions {
            adapter: lora.then(|| WeightSource::local(&fx.lora)),
            ..LoadOptions::default()
        },
    )
    .unwrap();
    let (tok, eos, pad) = load_tokenizer(model.llama_source()).unwrap();
    let proc = VlaadProcessor::new(tok, model.config(), eos, pad);
    (model, proc)
}

fn prompt(key: &str) -> &'static str {
    match key {
        "describe" => "Describe the dashcam clip.",
        "manoeuvre" => "What should the car do? Scene: Manoeuvres: Rationale:",
        other => panic!("unknown prompt {other}"),
    }
}

/// The reference's decoded frames of a case, as `FrameRef`s over `buf`.
fn frames_of(case: &serde_json::Value, buf: &[u8]) -> Vec<(u32, u32, std::ops::Range<usize>)> {
    let shape: Vec<usize> = case["frame_shape"]
        .as_array()
        .unwrap()
        .iter()
        .map(|x| x.as_u64().unwrap() as usize)
        .collect();
    let (t, h, w) = (shape[0], shape[1], shape[2]);
    assert_eq!(buf.len(), t * h * w * 3);
    (0..t)
        .map(|i| (w as u32, h as u32, i * h * w * 3..(i + 1) * h * w * 3))
        .collect()
}

#[test]
fn decoded_frames_match_the_repositorys_decord_within_a_grey_level() {
    let fx = fixture();
    let (_, proc) = load(&fx, false);
    let limits = vlmfuse_media::MediaLimits::default();
    for case in cases().iter().filter(|c| c["tag"] == "base") {
        let clip = data(case["clip"].as_str().unwrap());
        let info = vlmfuse_media::probe(&clip, &limits).unwrap();
        let times = proc.frame_times(info.duration_s, info.fps).unwrap();
        let s = proc.img_size as u32;
        let d = vlmfuse_media::sample_frames_at(
            &clip,
            &times,
            vlmfuse_media::FrameSize::Exact {
                width: s,
                height: s,
            },
            &limits,
            &vlmfuse_media::Interrupt::new(),
        )
        .unwrap();
        let ours: Vec<u8> = d.frames.iter().flat_map(|f| f.rgb.clone()).collect();
        let theirs = b64(&case["frames_u8"]);
        assert_eq!(ours.len(), theirs.len(), "{clip:?}: frame count or size");
        let worst = ours
            .iter()
            .zip(&theirs)
            .map(|(a, b)| (*a as i32 - *b as i32).abs())
            .max()
            .unwrap();
        let mean = ours
            .iter()
            .zip(&theirs)
            .map(|(a, b)| (*a as i32 - *b as i32).abs() as f64)
            .sum::<f64>()
            / ours.len() as f64;
        eprintln!("{clip:?}: max {worst} grey levels, mean {mean:.3}");
        assert!(worst <= 1, "{clip:?}: {worst} grey levels off decord");
        // The prompt's frame times are the decoded frames' own.
        let pts: Vec<f64> = d.frames.iter().map(|f| f.pts_s).collect();
        let text = proc.prompt("x", &pts);
        let msg = case["message"].as_str().unwrap();
        assert!(text.contains(msg.trim_end()), "{text:?} vs {msg:?}");
    }
}

#[test]
fn prompt_tokens_clip_tokens_logits_and_greedy_ids_match_the_repository() {
    let fx = fixture();
    let base = load(&fx, false);
    let tuned = load(&fx, true);
    let mut n = 0;
    for case in cases() {
        let (model, proc) = if case["tag"] == "lora" { &tuned } else { &base };
        let buf = b64(&case["frames_u8"]);
        let spans = frames_of(&case, &buf);
        let refs: Vec<FrameRef> = spans
            .iter()
            .map(|(w, h, r)| FrameRef {
                width: *w,
                height: *h,
                rgb: &buf[r.clone()],
            })
            .collect();
        // Times as the message states them (the reference rounds them to 0.1 s).
        let msg = case["message"].as_str().unwrap();
        let times: Vec<f64> = msg
            .split("sampled at ")
            .nth(1)
            .unwrap()
            .trim_end_matches(" seconds. ")
            .split(", ")
            .map(|x| x.parse().unwrap())
            .collect();
        let px = proc.preprocess(&refs, &times).unwrap();
        let plane = px.size * px.size;
        let d = max_abs_diff(&px.data[..3 * plane], &f32s(&case["pixels_frame0"]));
        assert!(d < 1e-6, "pixels off by {d}");
        let text = proc.prompt(prompt(case["prompt"].as_str().unwrap()), &px.times);
        assert_eq!(text, case["text"].as_str().unwrap(), "prompt text");
        let ids = proc
            .encode(&text, model.config().num_video_query_token)
            .unwrap();
        let pieces: Vec<Vec<u32>> = case["pieces"]
            .as_array()
            .unwrap()
            .iter()
            .map(|p| {
                p.as_array()
                    .unwrap()
                    .iter()
                    .map(|x| x.as_u64().unwrap() as u32)
                    .collect()
            })
            .collect();
        let mut want = pieces[0].clone();
        want.extend(std::iter::repeat_n(
            VISUAL_TOKEN,
            model.config().num_video_query_token,
        ));
        want.extend(&pieces[1]);
        assert_eq!(ids, want, "prompt ids");
        let tokens: Vec<f32> = model
            .clip_tokens(&px)
            .unwrap()
            .flatten_all()
            .unwrap()
            .to_vec1()
            .unwrap();
        let dt = max_abs_diff(&tokens, &f32s(&case["clip_tokens"]));
        let inp = ModelInputs {
            ids: proc.pad_left(vec![ids]),
            videos: vec![px],
        };
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
        let dl = max_abs_diff(&g.first_logits[0], &f32s(&case["logits"]));
        eprintln!(
            "{} {}: clip tokens {dt:.2e}, first-token logits {dl:.2e}",
            case["tag"], case["clip"]
        );
        assert!(dt < TOL, "clip tokens off by {dt}");
        assert!(dl < TOL, "first-token logits off by {dl}");
        let want: Vec<u32> = case["greedy"]
            .as_array()
            .unwrap()
            .iter()
            .map(|x| x.as_u64().unwrap() as u32)
            .collect();
        assert_eq!(g.tokens[0], want, "greedy ids");
        n += 1;
    }
    assert_eq!(n, 3);
    assert_eq!(tuned.0.merged_lora_keys().len(), 4);
}

#[test]
fn the_family_loads_by_model_type_and_asks_for_its_own_frames() {
    let fx = fixture();
    let fam = load_family(
        &WeightSource::local(&fx.release),
        &FamilyOptions {
            dtype: candle_core::DType::F32,
            device: candle_core::Device::Cpu,
            adapter: None,
            frames: None,
            prompt: prompt("describe").into(),
        },
    )
    .unwrap();
    assert_eq!(fam.model_type(), "vlaad");
    assert_eq!(fam.frame_size(), Some((28, 28)));
    // load_video over a 2 s, 10 fps clip: frames 0, 5, 10, 15.
    assert_eq!(
        fam.frame_times(2.0, 10.0).unwrap(),
        vec![0.0, 0.5, 1.0, 1.5]
    );
    // Frames of another size are scaled to the input; a batch of two clips runs.
    let clip = vlmfuse_testkit_models::fixtures::video_llava::PARITY_CLIPS[0].render();
    let p = fam.prepare(&[&clip, &clip[..3]]).unwrap();
    assert_eq!(fam.view(&p).unwrap().visual_tokens, vec![4, 4]);
    let g = fam
        .generate(&p, &GenerateOptions::greedy(3, fam.eos_ids()), None)
        .unwrap();
    assert_eq!(g.tokens.len(), 2);
}

#[test]
fn broken_releases_are_named_errors() {
    let fx = fixture();
    let cfg_path = fx.release.join("config.json");
    let good: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&cfg_path).unwrap()).unwrap();
    let err = |cfg: serde_json::Value| -> ModelError {
        std::fs::write(&cfg_path, serde_json::to_string(&cfg).unwrap()).unwrap();
        Vlaad::load(&WeightSource::local(&fx.release), &LoadOptions::default())
            .err()
            .expect("refused")
    };
    let mut c = good.clone();
    c["ckpt"] = "missing_run.pth".into();
    let e = err(c).to_string();
    assert!(e.contains("missing_run.pth"), "{e}");
    let mut c = good.clone();
    c.as_object_mut().unwrap().remove("vit_model");
    let e = err(c).to_string();
    assert!(e.contains("vit_model"), "{e}");
    let mut c = good.clone();
    c["model_type"] = "minigpt4".into();
    let e = err(c).to_string();
    assert!(e.contains("minigpt4"), "{e}");
    let mut c = good.clone();
    c["n_frms"] = 64.into();
    let e = err(c).to_string();
    assert!(e.contains("n_frms 64"), "{e}");
    // A truncated .pth names the file.
    std::fs::write(&cfg_path, serde_json::to_string(&good).unwrap()).unwrap();
    let p = fx.release.join("vlaad_checkpoint.pth");
    let bytes = std::fs::read(&p).unwrap();
    std::fs::write(&p, &bytes[..bytes.len() / 2]).unwrap();
    let e = Vlaad::load(&WeightSource::local(&fx.release), &LoadOptions::default())
        .err()
        .unwrap()
        .to_string();
    assert!(e.contains("vlaad_checkpoint.pth"), "{e}");
}
