//! Writes a random-weight model fixture to a directory, so reference scripts outside Rust
//! (`scripts/parity/qwen3_vl.py`, `scripts/bench/qwen3_vl.py`) read exactly the files the Rust
//! tests build.
//!
//! ```sh
//! cargo run -p vlmfuse-models --example write_fixture -- qwen3_vl DIR [--size tiny|mid] [--seed 7]
//! ```
//!
//! `tiny` is `TinyQwen3Vl::default()` (what the tests use); `mid` is the benchmark model
//! (text hidden 512, 8 layers; 16-pixel patches like the real checkpoints).

use std::path::PathBuf;
use std::process::ExitCode;

use vlmfuse_testkit_models::fixtures::TinyQwen3Vl;

fn usage() -> ExitCode {
    eprintln!("usage: write_fixture qwen3_vl DIR [--size tiny|mid] [--seed N]");
    ExitCode::from(2)
}

/// The mid-size benchmark model: a text tower the size of a small real LM layer stack, a vision
/// tower with the real patch geometry (16 px patches, 2x2 merge) so 8 frames of 256x256 give 256
/// visual tokens.
pub fn mid() -> TinyQwen3Vl {
    TinyQwen3Vl {
        vision_depth: 4,
        vision_hidden: 256,
        vision_heads: 4,
        vision_intermediate: 1024,
        patch_size: 16,
        merge_size: 2,
        num_position_embeddings: 256,
        deepstack_visual_indexes: vec![1, 2],
        hidden: 512,
        intermediate: 1536,
        layers: 8,
        heads: 8,
        kv_heads: 4,
        head_dim: 64,
    }
}

fn main() -> ExitCode {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let (mut model, mut dir, mut size, mut seed) = (None, None, "tiny".to_string(), 7u64);
    let mut it = args.into_iter();
    while let Some(a) = it.next() {
        match a.as_str() {
            "--size" => match it.next() {
                Some(s) => size = s,
                None => return usage(),
            },
            "--seed" => match it.next().and_then(|s| s.parse().ok()) {
                Some(s) => seed = s,
                None => return usage(),
            },
            "-h" | "--help" => return usage(),
            _ if model.is_none() => model = Some(a),
            _ if dir.is_none() => dir = Some(PathBuf::from(a)),
            _ => return usage(),
        }
    }
    let (Some(model), Some(dir)) = (model, dir) else {
        return usage();
    };
    if model != "qwen3_vl" {
        eprintln!("unknown model `{model}`; known: qwen3_vl");
        return ExitCode::from(2);
    }
    let fixture = match size.as_str() {
        "tiny" => TinyQwen3Vl::default(),
        "mid" => mid(),
        other => {
            eprintln!("unknown size `{other}`; known: tiny, mid");
            return ExitCode::from(2);
        }
    };
    match fixture.write(&dir, seed) {
        Ok(()) => {
            println!("{}", dir.display());
            ExitCode::SUCCESS
        }
        Err(e) => {
            eprintln!("write_fixture: {e}");
            ExitCode::FAILURE
        }
    }
}
