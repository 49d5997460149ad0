//! Writes the tiny VLAAD release (and a LoRA adapter on its LLaMA) to a directory, so
//! `scripts/parity/vlaad.py` runs the VLAAD repository's code on exactly the files the Rust
//! tests load.
//!
//! ```sh
//! cargo run -p vlmfuse-models --example vlaad_fixture -- /tmp/vlaad
//! ```
//! Layout: `DIR/release/` (`config.json`, the three `.pth` files, `llama-2-tiny/`),
//! `DIR/lora/` (PEFT adapter on the LLaMA). The clips the script decodes are committed under
//! `tests/data/parity/vlaad/`.

use std::path::PathBuf;

use vlmfuse_testkit_models::fixtures::TinyVlaad;

/// Seeds shared with the parity tests (tests/vlaad_parity.rs).
const MODEL_SEED: u64 = 9;
const ADAPTER_SEED: u64 = 29;

fn main() {
    let Some(dir) = std::env::args().nth(1).map(PathBuf::from) else {
        eprintln!("usage: vlaad_fixture DIR [--mid]");
        std::process::exit(2);
    };
    let mid = std::env::args().any(|a| a == "--mid");
    let run = || -> anyhow::Result<()> {
        let t = if mid {
            TinyVlaad::mid()
        } else {
            TinyVlaad::default()
        };
        t.write(&dir.join("release"), MODEL_SEED)?;
        t.write_lora_adapter(&dir.join("lora"), 4, 8.0, ADAPTER_SEED)?;
        Ok(())
    };
    if let Err(e) = run() {
        eprintln!("error: {e}");
        std::process::exit(1);
    }
    println!("wrote {}", dir.display());
}
