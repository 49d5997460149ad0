//! Time to first token and decode tokens/s of the in-process VideoLLaVA on CPU, against
//! transformers on the same weights and inputs in the same run.
//!
//! ```sh
//! cargo run --release -p vlmfuse-models --example video_llava_fixture -- /tmp/vl          # tiny
//! cargo run --release -p vlmfuse-models --example video_llava_fixture -- /tmp/vlm --mid   # mid
//! cargo build --release -p vlmfuse-models --example video_llava_bench
//! ${CARGO_TARGET_DIR:-target}/release/examples/video_llava_bench /tmp/vlm \
//!     --python "$PYTHON" [--new-tokens 32] [--repeats 3] [--threads N]
//! ```
//! Input: the fixture's `landscape` clip (8 frames) with the "describe" prompt. TTFT is from
//! decoded frames to the first token (preprocessing, vision tower, projector, prefill); decode
//! tokens/s counts the tokens after the first. Both sides decode exactly `--new-tokens` tokens
//! (no EOS), take the best of `--repeats`, and use every core.

use std::path::PathBuf;
use std::process::Command;
use std::time::Instant;

use vlmfuse_models::generate::{generate_with, GenerateOptions};
use vlmfuse_models::models::video_llava::{LoadOptions, VideoLlava, VideoLlavaProcessor};
use vlmfuse_models::{FrameRef, WeightSource};
use vlmfuse_testkit_models::fixtures::video_llava::PARITY_CLIPS;

struct Args {
    dir: PathBuf,
    python: Option<String>,
    new_tokens: usize,
    repeats: usize,
    threads: Option<usize>,
}

fn args() -> Args {
    let mut it = std::env::args().skip(1);
    let mut a = Args {
        dir: PathBuf::new(),
        python: None,
        new_tokens: 32,
        repeats: 3,
        threads: None,
    };
    let mut dir = None;
    while let Some(x) = it.next() {
        let mut num = |what: &str| -> usize {
            it.next()
                .and_then(|v| v.parse().ok())
                .unwrap_or_else(|| panic!("{what} needs a number"))
        };
        match x.as_str() {
            "--new-tokens" => a.new_tokens = num("--new-tokens").max(2),
            "--repeats" => a.repeats = num("--repeats").max(1),
            "--threads" => a.threads = Some(num("--threads").max(1)),
            "--python" => a.python = it.next(),
            _ => dir = Some(PathBuf::from(x)),
        }
    }
    a.dir = dir.unwrap_or_else(|| {
        eprintln!("usage: video_llava_bench DIR [--python PY] [--new-tokens N] [--repeats R]");
        std::process::exit(2)
    });
    a
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let a = args();
    if let Some(n) = a.threads {
        // candle sizes its CPU thread use from this variable on first use.
        std::env::set_var("RAYON_NUM_THREADS", n.to_string());
    }
    let src = WeightSource::local(a.dir.join("model"));
    let t = Instant::now();
    let model = VideoLlava::load(&src, &LoadOptions::default())?;
    let proc = VideoLlavaProcessor::load(&src, model.config())?;
    let load_s = t.elapsed().as_secs_f64();
    let clip = PARITY_CLIPS.iter().find(|c| c.name == "landscape").unwrap();
    let frames = clip.render();
    let refs: Vec<FrameRef> = frames.iter().map(|f| f.as_ref()).collect();
    let text = proc.video_prompt("Describe the dashcam clip.");
    let mut cache = model.new_cache(1024);

    let (mut best_ttft, mut best_tps, mut prompt) = (f64::MAX, 0f64, 0);
    for _ in 0..a.repeats + 1 {
        let t0 = Instant::now();
        let inputs = proc.prepare_videos(&[(text.as_str(), refs.as_slice())])?;
        let pre = t0.elapsed();
        let g = generate_with(
            &model,
            &inputs,
            &mut cache,
            &GenerateOptions::greedy(a.new_tokens, &[]),
            None,
        )?;
        let ttft = (pre + g.prefill).as_secs_f64();
        let tps = (a.new_tokens - 1) as f64 / g.decode.as_secs_f64().max(1e-9);
        prompt = inputs.ids.seq_len();
        best_ttft = best_ttft.min(ttft);
        best_tps = best_tps.max(tps);
    }
    // Where the first token's time goes (best of the repeats again).
    let (mut pre_s, mut vis_s) = (f64::MAX, f64::MAX);
    for _ in 0..a.repeats {
        let t = Instant::now();
        let inputs = proc.prepare_videos(&[(text.as_str(), refs.as_slice())])?;
        pre_s = pre_s.min(t.elapsed().as_secs_f64());
        let t = Instant::now();
        model.video_features(&inputs.videos)?;
        vis_s = vis_s.min(t.elapsed().as_secs_f64());
    }
    let c = model.config();
    println!(
        "model: text hidden {} x {} layers, vocab {}, tower {} x {} layers at {}px ({} tokens/frame); \
         prompt {prompt} tokens; load {load_s:.2}s",
        c.text.hidden_size,
        c.text.num_hidden_layers,
        c.text.vocab_size,
        c.vision.hidden_size,
        c.vision.num_hidden_layers,
        c.vision.image_size,
        c.vision.tokens_per_frame()
    );
    println!(
        "vlmfuse (candle, f32, CPU): TTFT {:.1} ms (preprocess {:.1}, vision+projector {:.1}, \
         text prefill ~{:.1}), decode {:.1} tok/s",
        best_ttft * 1e3,
        pre_s * 1e3,
        vis_s * 1e3,
        (best_ttft - pre_s - vis_s).max(0.0) * 1e3,
        best_tps
    );
    if let Some(py) = &a.python {
        let script =
            PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../scripts/parity/video_llava.py");
        let out = Command::new(py)
            .arg(&script)
            .arg(&a.dir)
            .args(["--bench", "--new-tokens", &a.new_tokens.to_string()])
            .args(["--repeats", &a.repeats.to_string()])
            .args(
                a.threads
                    .map(|n| vec!["--threads".to_string(), n.to_string()])
                    .unwrap_or_default(),
            )
            .output()?;
        if !out.status.success() {
            eprintln!("{}", String::from_utf8_lossy(&out.stderr));
            return Err("the transformers benchmark failed".into());
        }
        let line = String::from_utf8_lossy(&out.stdout);
        let j: serde_json::Value = serde_json::from_str(line.lines().last().unwrap_or("{}"))?;
        let (pt, pd) = (
            j["ttft_s"].as_f64().unwrap_or(f64::NAN),
            j["decode_tok_s"].as_f64().unwrap_or(f64::NAN),
        );
        println!(
            "transformers {} (torch, f32, CPU, {} threads): TTFT {:.1} ms, decode {:.1} tok/s",
            j["version"].as_str().unwrap_or("?"),
            j["threads"],
            pt * 1e3,
            pd
        );
        println!(
            "ratio (vlmfuse / transformers): TTFT speed-up {:.2}x, decode {:.2}x",
            pt / best_ttft,
            best_tps / pd
        );
    }
    Ok(())
}
