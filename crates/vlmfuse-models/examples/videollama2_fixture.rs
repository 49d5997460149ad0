//! Writes the tiny VideoLLaMA2 fixtures (and a LoRA run and the synthetic clips) to a
//! directory, so `scripts/parity/videollama2.py` runs the VideoLLaMA2 repository's code on
//! exactly the files the Rust tests load.
//!
//! ```sh
//! cargo run -p vlmfuse-models --example videollama2_fixture -- /tmp/vl2
//! ```
//! Layout: `DIR/mistral-base/` (the checkpoint, `image_aspect_ratio = pad`, its tower in
//! `clip-vision-tower/`), `DIR/mistral-crop/` (the same weights, no padding to square),
//! `DIR/mistral-notemplate/` (no chat template), `DIR/videollama2-lora/` (a LoRA run on the
//! base), `DIR/frames/` (raw RGB clips + `frames.json`). The directory names matter to the
//! repository's loader (`mistral` picks the Mistral class, `lora` the LoRA branch, `clip` the
//! tower).

use std::path::PathBuf;

use vlmfuse_testkit_models::fixtures::video_llava::write_parity_frames;
use vlmfuse_testkit_models::fixtures::TinyVideoLlama2;

/// Seeds shared with the parity tests (tests/videollama2_parity.rs).
const MODEL_SEED: u64 = 5;
const ADAPTER_SEED: u64 = 23;

fn main() {
    let Some(dir) = std::env::args().nth(1).map(PathBuf::from) else {
        eprintln!("usage: videollama2_fixture DIR [--mid]");
        std::process::exit(2);
    };
    if std::env::args().any(|a| a == "--mid") {
        // The benchmark's checkpoint only (examples/family_bench.rs).
        let r = TinyVideoLlama2::mid().write(&dir.join("mistral-base"), MODEL_SEED);
        if let Err(e) = r.and_then(|_| write_parity_frames(&dir.join("frames"))) {
            eprintln!("error: {e}");
            std::process::exit(1);
        }
        println!("wrote {}", dir.display());
        return;
    }
    let run = || -> anyhow::Result<()> {
        let base = TinyVideoLlama2::default();
        base.write(&dir.join("mistral-base"), MODEL_SEED)?;
        TinyVideoLlama2 {
            aspect_ratio: "no",
            ..TinyVideoLlama2::default()
        }
        .write(&dir.join("mistral-crop"), MODEL_SEED)?;
        TinyVideoLlama2 {
            no_template: true,
            ..TinyVideoLlama2::default()
        }
        .write(&dir.join("mistral-notemplate"), MODEL_SEED)?;
        base.write_lora_run(
            &dir.join("videollama2-lora"),
            &std::fs::canonicalize(dir.join("mistral-base"))?,
            4,
            8.0,
            ADAPTER_SEED,
        )?;
        write_parity_frames(&dir.join("frames"))?;
        Ok(())
    };
    if let Err(e) = run() {
        eprintln!("error: {e}");
        std::process::exit(1);
    }
    println!("wrote {}", dir.display());
}
