//! `vlmfuse describe CLIP --config FILE --reporter NAME [--dump DIR]` on both tiny in-process
//! fixtures: the answer and its labels, the dump files with their shapes, and the dumped
//! generated ids equal to what the model crate's own greedy decoding gives for the dumped
//! inputs; then the errors (unknown reporter, missing clip, a file that is no video).

use crate::support::BIN;
use candle_core::Tensor;
use serde_json::Value;
use std::path::Path;
use std::process::{Command, Output};
use vlmfuse_models::generate::{generate, GenerateOptions};
use vlmfuse_models::models::qwen3_vl::{self, Qwen3Vl, Qwen3VlProcessor, Sequence, VideoInput};
use vlmfuse_models::models::video_llava::{
    self, EncodedBatch, ModelInputs, VideoLlava, VideoLlavaProcessor, VideoPixels,
};
use vlmfuse_models::WeightSource;
use vlmfuse_testkit::clips::h264_clip;
use vlmfuse_testkit::server::{FakeOpenAi, LABELER_LABELS};
use vlmfuse_testkit_models::fixtures::{TinyQwen3Vl, TinyVideoLlama2, TinyVideoLlava, TinyVlaad};

const MAX_NEW: usize = 6;

struct Setup {
    _tmp: tempfile::TempDir,
    _fake: FakeOpenAi,
    dir: std::path::PathBuf,
    config: std::path::PathBuf,
    clip: std::path::PathBuf,
    qwen: std::path::PathBuf,
    llava: std::path::PathBuf,
    llama2: std::path::PathBuf,
    vlaad: std::path::PathBuf,
}

fn setup() -> Setup {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().to_path_buf();
    let fake = FakeOpenAi::start();
    let qwen = dir.join("qwen");
    TinyQwen3Vl::default().write(&qwen, 7).unwrap();
    let llava = dir.join("llava");
    TinyVideoLlava::default().write(&llava, 7).unwrap();
    let llama2 = dir.join("videollama2");
    TinyVideoLlama2::default().write(&llama2, 5).unwrap();
    let vlaad = dir.join("vlaad");
    TinyVlaad::default().write(&vlaad, 9).unwrap();
    let mut cfg = String::from(
        "reporters = [\"q\", \"v\", \"l2\", \"a\", \"remote\"]\n\n[media]\nframes = 6\n\n",
    );
    for (name, d) in [("q", &qwen), ("v", &llava), ("l2", &llama2), ("a", &vlaad)] {
        cfg += &format!(
            "[[reporter]]\nkind = \"candle\"\nname = \"{name}\"\nweights = {{ path = {d:?} }}\n\
             max_new_tokens = {MAX_NEW}\nprompt = \"describe the dashcam clip\"\n\n"
        );
    }
    cfg += &fake.reporter_toml("remote", "frames");
    cfg += &fake.labeler_toml();
    let config = dir.join("vlmfuse.toml");
    std::fs::write(&config, cfg).unwrap();
    let clip = h264_clip(&dir, "drive.mp4", "testsrc2", 2.0);
    Setup {
        _tmp: tmp,
        _fake: fake,
        dir,
        config,
        clip,
        qwen,
        llava,
        llama2,
        vlaad,
    }
}

fn describe(s: &Setup, clip: &Path, extra: &[&str]) -> Output {
    Command::new(BIN)
        .arg("describe")
        .arg(clip)
        .arg("--config")
        .arg(&s.config)
        .arg("--quiet")
        .args(extra)
        .env_remove("VLMFUSE_CONFIG")
        .output()
        .unwrap()
}

fn json_file(p: &Path) -> Value {
    serde_json::from_str(&std::fs::read_to_string(p).unwrap()).unwrap()
}

fn ids(v: &Value) -> Vec<u32> {
    v.as_array()
        .unwrap()
        .iter()
        .map(|x| x.as_u64().unwrap() as u32)
        .collect()
}

fn ok(out: &Output) -> String {
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "exit {:?}: {err}", out.status.code());
    String::from_utf8(out.stdout.clone()).unwrap()
}

#[test]
fn describe_dumps_what_the_model_crate_computes_on_both_fixtures() {
    let s = setup();
    for (name, model_type) in [("q", "qwen3_vl"), ("v", "video_llava")] {
        let dump = s.dir.join(format!("dump-{name}"));
        let text = ok(&describe(
            &s,
            &s.clip,
            &["--reporter", name, "--dump", dump.to_str().unwrap()],
        ));
        assert!(text.contains("answer:"), "{text}");
        assert!(
            text.contains(&format!("labels: {}", LABELER_LABELS.join(", "))),
            "{text}"
        );
        for f in [
            "input_ids.json",
            "pixel_values.npy",
            "grid.json",
            "first_token_logits.npy",
            "generated_ids.json",
            "meta.json",
            "frames.json",
            "step_logits.npy",
            "generated_steps.json",
        ] {
            assert!(dump.join(f).is_file(), "{name}: {f} missing");
        }
        check_steps(&dump);
        let input_ids = ids(&json_file(&dump.join("input_ids.json")));
        let grid = json_file(&dump.join("grid.json"));
        let generated = ids(&json_file(&dump.join("generated_ids.json")));
        assert_eq!(json_file(&dump.join("meta.json"))["model_type"], model_type);
        assert!(!generated.is_empty() && generated.len() <= MAX_NEW);
        let px = Tensor::read_npy(dump.join("pixel_values.npy")).unwrap();
        let logits = Tensor::read_npy(dump.join("first_token_logits.npy")).unwrap();

        let want = match model_type {
            "qwen3_vl" => {
                let src = WeightSource::local(&s.qwen);
                let m = Qwen3Vl::load(&src, &qwen3_vl::LoadOptions::default()).unwrap();
                let p = Qwen3VlProcessor::load(&src, m.config()).unwrap();
                assert_eq!(logits.dims(), &[m.config().text.vocab_size]);
                let (t, h, w) = (
                    grid["t"].as_u64().unwrap() as usize,
                    grid["h"].as_u64().unwrap() as usize,
                    grid["w"].as_u64().unwrap() as usize,
                );
                // The checkpoint's sampler, not `[media] frames = 6`: 2 fps of a 2 s clip at
                // 10 fps are 4 frames, `linspace(0, 19, 4).round()`, = 2 temporal groups.
                assert_eq!(t, 2, "{grid}");
                let fr = json_file(&dump.join("frames.json"));
                assert_eq!(fr["sampler"], "checkpoint", "{fr}");
                assert_eq!(fr["indices"], serde_json::json!([0, 6, 13, 19]), "{fr}");
                assert_eq!(fr["media"]["frames"], 6, "{fr}");
                let hashes = fr["sha256"].as_array().unwrap();
                assert_eq!(hashes.len(), 4, "{fr}");
                assert!(
                    hashes.iter().all(|h| h.as_str().unwrap().len() == 64),
                    "{fr}"
                );
                let meta = json_file(&dump.join("meta.json"));
                assert!(!meta["eos_ids"].as_array().unwrap().is_empty(), "{meta}");
                assert_eq!(meta["prompt"], "describe the dashcam clip", "{meta}");
                assert_eq!(px.dims(), &[t * h * w, m.config().vision.patch_dim()]);
                let seq = Sequence {
                    ids: input_ids,
                    video: Some(VideoInput {
                        pixel_values: px.flatten_all().unwrap().to_vec1().unwrap(),
                        grid_thw: [t, h, w],
                    }),
                };
                generate(
                    &m,
                    &vec![seq],
                    &GenerateOptions::greedy(MAX_NEW, p.eos_ids()),
                    None,
                )
                .unwrap()
                .tokens
                .remove(0)
            }
            _ => {
                let src = WeightSource::local(&s.llava);
                let m = VideoLlava::load(&src, &video_llava::LoadOptions::default()).unwrap();
                let p = VideoLlavaProcessor::load(&src, m.config()).unwrap();
                assert_eq!(logits.dims(), &[m.config().text.vocab_size]);
                let (f, h, w) = (
                    grid["frames"].as_u64().unwrap() as usize,
                    grid["height"].as_u64().unwrap() as usize,
                    grid["width"].as_u64().unwrap() as usize,
                );
                // The processor's frame count is 8; the clip has 6 sampled frames.
                assert_eq!(f, 6, "{grid}");
                assert_eq!(px.dims(), &[f, 3, h, w]);
                let n = input_ids.len();
                let inputs = ModelInputs {
                    ids: EncodedBatch {
                        input_ids: vec![input_ids],
                        attention_mask: vec![vec![true; n]],
                    },
                    videos: vec![VideoPixels {
                        data: px.flatten_all().unwrap().to_vec1().unwrap(),
                        frames: f,
                        height: h,
                        width: w,
                    }],
                    images: Vec::new(),
                };
                generate(
                    &m,
                    &inputs,
                    &GenerateOptions::greedy(MAX_NEW, &p.eos_token_ids),
                    None,
                )
                .unwrap()
                .tokens
                .remove(0)
            }
        };
        assert_eq!(generated, want, "{name}: generated ids");
        let first = logits.to_vec1::<f32>().unwrap();
        let argmax = first
            .iter()
            .enumerate()
            .fold(0, |b, (i, &x)| if x > first[b] { i } else { b });
        assert_eq!(argmax as u32, generated[0], "{name}: first token");

        // --json: the same ids.
        let v: Value = serde_json::from_str(&ok(&describe(
            &s,
            &s.clip,
            &["--reporter", name, "--json", "--no-labels"],
        )))
        .unwrap();
        assert_eq!(ids(&v["generated_ids"]), generated, "{v}");
        assert_eq!(v["model_type"], model_type);
        assert!(v.get("labels").is_none());
    }
}

/// `step_logits.npy` holds one row per generated token (the stop token's too) whose first row
/// is `first_token_logits.npy`; `generated_steps.json` names the ids and their log-probabilities.
fn check_steps(dump: &Path) {
    let steps = Tensor::read_npy(dump.join("step_logits.npy")).unwrap();
    let first = Tensor::read_npy(dump.join("first_token_logits.npy"))
        .unwrap()
        .to_vec1::<f32>()
        .unwrap();
    let rows = steps.to_vec2::<f32>().unwrap();
    assert_eq!(rows[0], first);
    let generated = ids(&json_file(&dump.join("generated_ids.json")));
    let meta = json_file(&dump.join("meta.json"));
    let eos: Vec<u32> = ids(&meta["eos_ids"]);
    let st = json_file(&dump.join("generated_steps.json"));
    let st = st.as_array().unwrap();
    assert_eq!(st.len(), rows.len());
    assert!(rows.len() == generated.len() || rows.len() == generated.len() + 1);
    for (i, (row, s)) in rows.iter().zip(st).enumerate() {
        let id = s["id"].as_u64().unwrap() as u32;
        if i < generated.len() {
            assert_eq!(id, generated[i]);
        } else {
            assert!(eos.contains(&id), "the extra row is the stop token: {id}");
        }
        // Greedy: the id is the row's argmax, and its log-probability is the largest.
        let argmax = row
            .iter()
            .enumerate()
            .fold(0, |b, (j, &x)| if x > row[b] { j } else { b });
        assert_eq!(argmax as u32, id, "step {i}");
        let lp = s["logprob"].as_f64().unwrap();
        assert!(lp <= 0.0 && lp > -50.0, "{s}");
    }
}

/// The two repository families: their dumps, their own samplers (`frames.json`), and the
/// dumped ids equal to the model crate's greedy decoding of the dumped inputs.
#[test]
fn describe_dumps_the_videollama2_and_vlaad_families() {
    use vlmfuse_models::models::{videollama2, vlaad};
    let s = setup();
    for (name, model_type) in [("l2", "videollama2"), ("a", "vlaad")] {
        let dump = s.dir.join(format!("dump-{name}"));
        let text = ok(&describe(
            &s,
            &s.clip,
            &["--reporter", name, "--dump", dump.to_str().unwrap()],
        ));
        assert!(text.contains("answer:"), "{text}");
        check_steps(&dump);
        assert_eq!(json_file(&dump.join("meta.json"))["model_type"], model_type);
        let fr = json_file(&dump.join("frames.json"));
        assert_eq!(fr["sampler"], "checkpoint", "{fr}");
        let input_ids = ids(&json_file(&dump.join("input_ids.json")));
        let generated = ids(&json_file(&dump.join("generated_ids.json")));
        let px = Tensor::read_npy(dump.join("pixel_values.npy")).unwrap();
        let n = input_ids.len();
        let batch = EncodedBatch {
            input_ids: vec![input_ids],
            attention_mask: vec![vec![true; n]],
        };
        let data: Vec<f32> = px.flatten_all().unwrap().to_vec1().unwrap();
        let want = if model_type == "videollama2" {
            // frame_sample(20 frames, 4): the middles of four equal segments.
            assert_eq!(fr["indices"], serde_json::json!([2, 7, 12, 17]), "{fr}");
            let (m, _) = videollama2::VideoLlama2::load(
                &WeightSource::local(&s.llama2),
                &videollama2::LoadOptions::default(),
            )
            .unwrap();
            let d = px.dims().to_vec();
            assert_eq!(d, vec![4, 3, 35, 35]);
            let inputs = videollama2::ModelInputs {
                ids: batch,
                videos: vec![VideoPixels {
                    data,
                    frames: d[0],
                    height: d[2],
                    width: d[3],
                }],
            };
            generate(&m, &inputs, &GenerateOptions::greedy(MAX_NEW, &[2]), None)
                .unwrap()
                .tokens
                .remove(0)
        } else {
            // load_video's np.arange(0, 20, 5), decoded at the model's 28x28.
            assert_eq!(fr["indices"], serde_json::json!([0, 5, 10, 15]), "{fr}");
            assert!(
                fr["sizes"]
                    .as_array()
                    .unwrap()
                    .iter()
                    .all(|z| *z == serde_json::json!([28, 28])),
                "{fr}"
            );
            let m = vlaad::Vlaad::load(
                &WeightSource::local(&s.vlaad),
                &vlaad::LoadOptions::default(),
            )
            .unwrap();
            let d = px.dims().to_vec();
            assert_eq!(d, vec![4, 3, 28, 28]);
            let inputs = vlaad::ModelInputs {
                ids: batch,
                videos: vec![vlaad::ClipPixels {
                    data,
                    frames: d[0],
                    size: d[2],
                    times: vec![0.0, 0.5, 1.0, 1.5],
                }],
            };
            generate(&m, &inputs, &GenerateOptions::greedy(MAX_NEW, &[2]), None)
                .unwrap()
                .tokens
                .remove(0)
        };
        assert_eq!(generated, want, "{name}: generated ids");
    }
}

#[test]
fn describe_errors_are_clear() {
    let s = setup();
    let out = describe(&s, &s.clip, &["--reporter", "nope"]);
    assert_eq!(out.status.code(), Some(1));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("no reporter `nope`") && err.contains("configured: q, v, l2, a, remote"),
        "{err}"
    );

    let out = describe(&s, &s.dir.join("missing.mp4"), &["--reporter", "q"]);
    assert_eq!(out.status.code(), Some(1));
    assert!(
        String::from_utf8_lossy(&out.stderr).contains("does not exist"),
        "{out:?}"
    );

    let junk = s.dir.join("junk.mp4");
    std::fs::write(&junk, b"this is not a video container at all").unwrap();
    let out = describe(&s, &junk, &["--reporter", "q"]);
    assert_eq!(out.status.code(), Some(1), "{out:?}");
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("decoding") && err.contains("junk.mp4"),
        "{err}"
    );

    let out = describe(&s, &s.clip, &["--reporter", "remote", "--dump", "/tmp/x"]);
    assert_eq!(out.status.code(), Some(1));
    assert!(
        String::from_utf8_lossy(&out.stderr).contains("kind = \"candle\""),
        "{out:?}"
    );

    // A remote reporter answers through its server.
    let text = ok(&describe(&s, &s.clip, &["--reporter", "remote"]));
    assert!(
        text.contains("answer:") && text.contains("labels:"),
        "{text}"
    );
}
