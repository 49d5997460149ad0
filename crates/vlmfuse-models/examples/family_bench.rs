//! Time to first token and decode tokens/s of an in-process family on CPU against its
//! reference repository's code on the same weights and inputs, in one run (VideoLLaMA2 and
//! VLAAD; VideoLLaVA and Qwen3-VL have their own benches against transformers).
//!
//! ```sh
//! cargo run --release -p vlmfuse-models --example videollama2_fixture -- /tmp/vl2m --mid
//! cargo run --release -p vlmfuse-models --example vlaad_fixture -- /tmp/vlaadm --mid
//! cargo run --release -p vlmfuse-models --example family_bench -- videollama2 /tmp/vl2m \
//!     --python /work/ref-vl2/bin/python --repo /work/ref-src/VideoLLaMA2
//! cargo run --release -p vlmfuse-models --example family_bench -- vlaad /tmp/vlaadm \
//!     --python /work/ref-vlaad/bin/python --repo /work/ref-src/vlaad
//! ```
//! Inputs: VideoLLaMA2 the `landscape` clip's 8 frames, VLAAD `tests/data/parity/vlaad/clip20.mp4`
//! decoded once (untimed) at the model's size; the "describe" prompt. TTFT runs from decoded
//! frames to the first token; then exactly `--new-tokens` greedy tokens (no EOS); best of
//! `--repeats`; every core on both sides.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;

use vlmfuse_models::generate::GenerateOptions;
use vlmfuse_models::models::family::{load_family, FamilyOptions};
use vlmfuse_models::{Frame, WeightSource};
use vlmfuse_testkit_models::fixtures::video_llava::PARITY_CLIPS;

fn main() {
    let mut it = std::env::args().skip(1);
    let (mut family, mut dir, mut python, mut repo) = (None, None, None, None);
    let (mut new_tokens, mut repeats) = (32usize, 3usize);
    while let Some(a) = it.next() {
        match a.as_str() {
            "--python" => python = it.next(),
            "--repo" => repo = it.next(),
            "--new-tokens" => {
                new_tokens = it.next().and_then(|x| x.parse().ok()).unwrap_or(32).max(2)
            }
            "--repeats" => repeats = it.next().and_then(|x| x.parse().ok()).unwrap_or(3).max(1),
            _ if family.is_none() => family = Some(a),
            _ => dir = Some(PathBuf::from(a)),
        }
    }
    let (Some(family), Some(dir)) = (family, dir) else {
        eprintln!("usage: family_bench videollama2|vlaad DIR [--python PY --repo REPO] [--new-tokens N] [--repeats R]");
        std::process::exit(2);
    };
    let data = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../tests/data/parity/vlaad");
    let (weights, frames, script): (PathBuf, Vec<Frame>, &str) = match family.as_str() {
        "videollama2" => (
            dir.join("mistral-base"),
            PARITY_CLIPS
                .iter()
                .find(|c| c.name == "landscape")
                .unwrap()
                .render(),
            "scripts/parity/videollama2.py",
        ),
        "vlaad" => {
            let clip = data.join("clip20.mp4");
            let limits = vlmfuse_media::MediaLimits::default();
            let info = vlmfuse_media::probe(&clip, &limits).expect("probe");
            let cfg: serde_json::Value = serde_json::from_str(
                &std::fs::read_to_string(dir.join("release/config.json")).unwrap(),
            )
            .unwrap();
            let (n, s) = (
                cfg["n_frms"].as_u64().unwrap() as usize,
                cfg["img_size"].as_u64().unwrap() as u32,
            );
            let total = (info.duration_s * info.fps).round() as usize;
            let step = total as f64 / n.min(total) as f64;
            let times: Vec<f64> = (0..n.min(total))
                .map(|i| ((i as f64 * step) as usize) as f64 / info.fps)
                .collect();
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
            .expect("decode");
            (
                dir.join("release"),
                d.frames.into_iter().map(|f| f.frame).collect(),
                "scripts/parity/vlaad.py",
            )
        }
        other => {
            eprintln!("unknown family {other} (videollama2, vlaad)");
            std::process::exit(2);
        }
    };
    let fam = load_family(
        &WeightSource::local(&weights),
        &FamilyOptions {
            dtype: candle_core::DType::F32,
            device: candle_core::Device::Cpu,
            adapter: None,
            frames: None,
            prompt: "Describe the dashcam clip.".into(),
        },
    )
    .expect("load");
    let run = |n: usize| -> (f64, usize) {
        let t0 = Instant::now();
        let p = fam.prepare(&[&frames]).expect("prepare");
        let g = fam
            .generate(&p, &GenerateOptions::greedy(n, &[]), None)
            .expect("generate");
        assert_eq!(g.tokens[0].len(), n);
        (
            t0.elapsed().as_secs_f64(),
            fam.view(&p).unwrap().prompt_tokens[0],
        )
    };
    run(2);
    if let Some(f) = fam
        .as_any()
        .downcast_ref::<vlmfuse_models::models::videollama2::VideoLlama2Family>()
    {
        // Where the first token's time goes.
        let refs: Vec<_> = frames.iter().map(Frame::as_ref).collect();
        let t0 = Instant::now();
        let v = f.processor.preprocess_video(&refs).unwrap();
        let t1 = Instant::now();
        let _ = f.model.video_features(std::slice::from_ref(&v)).unwrap();
        let t2 = Instant::now();
        eprintln!(
            "videollama2: preprocess {:.1} ms, tower + connector {:.1} ms",
            (t1 - t0).as_secs_f64() * 1e3,
            (t2 - t1).as_secs_f64() * 1e3
        );
    }
    let ttft = (0..repeats).map(|_| run(1).0).fold(f64::INFINITY, f64::min);
    let (full, prompt) = (0..repeats)
        .map(|_| run(new_tokens))
        .fold((f64::INFINITY, 0), |a, b| if b.0 < a.0 { b } else { a });
    let tps = (new_tokens - 1) as f64 / (full - ttft).max(1e-9);
    println!(
        "{}",
        serde_json::json!({"impl": "vlmfuse", "family": family, "ttft_s": ttft, "decode_tok_s": tps,
            "prompt_tokens": prompt, "new_tokens": new_tokens})
    );
    if let (Some(py), Some(repo)) = (python, repo) {
        let out = Command::new(py)
            .args([script, dir.to_str().unwrap(), "--repo", &repo, "--bench"])
            .args([
                "--new-tokens",
                &new_tokens.to_string(),
                "--repeats",
                &repeats.to_string(),
            ])
            .current_dir(Path::new(env!("CARGO_MANIFEST_DIR")).join("../.."))
            .output()
            .expect("running the reference");
        let text = String::from_utf8_lossy(&out.stdout);
        let Some(line) = text.lines().rev().find(|l| l.starts_with('{')) else {
            eprintln!(
                "reference printed no result:\n{}",
                String::from_utf8_lossy(&out.stderr)
            );
            std::process::exit(1);
        };
        println!("{line}");
        let r: serde_json::Value = serde_json::from_str(line).unwrap();
        let (rt, rd) = (
            r["ttft_s"].as_f64().unwrap(),
            r["decode_tok_s"].as_f64().unwrap(),
        );
        println!(
            "{family}: TTFT {:.1} ms vs {:.1} ms (reference / ours = {:.2}x); decode {:.1} vs {:.1} tok/s ({:.2}x)",
            ttft * 1e3,
            rt * 1e3,
            rt / ttft,
            tps,
            rd,
            tps / rd
        );
    }
}
