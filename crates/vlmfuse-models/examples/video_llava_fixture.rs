//! Writes the tiny VideoLLaVA fixture (and its LoRA adapter and synthetic clips) to a directory,
//! so `scripts/parity/video_llava.py` runs transformers on exactly the files the Rust tests load.
//!
//! ```sh
//! cargo run -p vlmfuse-models --example video_llava_fixture -- /tmp/vl          # tiny
//! cargo run -p vlmfuse-models --example video_llava_fixture -- /tmp/vlm --mid    # benchmark
//! ```
//! Layout: `DIR/model/` (the checkpoint), `DIR/adapter/` (PEFT, transformers 5 names),
//! `DIR/frames/` (raw RGB clips + `frames.json`).

use std::path::PathBuf;

use vlmfuse_models::models::video_llava::transformers5_name;
use vlmfuse_testkit_models::fixtures::video_llava::write_parity_frames;
use vlmfuse_testkit_models::fixtures::TinyVideoLlava;

/// Seeds shared with the parity tests (tests/video_llava_parity.rs).
const MODEL_SEED: u64 = 7;
const ADAPTER_SEED: u64 = 21;

fn main() {
    let mut args = std::env::args().skip(1);
    let Some(dir) = args.next().map(PathBuf::from) else {
        eprintln!("usage: video_llava_fixture DIR [--mid]");
        std::process::exit(2);
    };
    let mid = args.any(|a| a == "--mid");
    let shape = if mid {
        TinyVideoLlava::mid()
    } else {
        TinyVideoLlava::default()
    };
    let run = || -> anyhow::Result<()> {
        shape.write(&dir.join("model"), MODEL_SEED)?;
        if !mid {
            shape.write_lora_adapter(
                &dir.join("adapter"),
                4,
                8.0,
                ADAPTER_SEED,
                Some(transformers5_name),
            )?;
        }
        write_parity_frames(&dir.join("frames"))?;
        Ok(())
    };
    if let Err(e) = run() {
        eprintln!("error: {e}");
        std::process::exit(1);
    }
    println!("wrote {}", dir.display());
}
