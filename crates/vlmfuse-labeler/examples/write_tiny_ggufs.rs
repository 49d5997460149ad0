//! Writes the tiny random GGUF files of every family into a directory, for
//! `tests/data/labeler/gguf/reference.py` to compute transformers' reference outputs on.
//!
//! ```text
//! cargo run -p vlmfuse-labeler --example write_tiny_ggufs -- DIR
//! ```
//! The tests regenerate the same files (same seed) and check their fingerprint against the one
//! the reference recorded, so the reference always describes the file under test.

use vlmfuse_labeler::tiny_gguf;
use vlmfuse_models::text::gguf::Family;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let dir = std::env::args()
        .nth(1)
        .ok_or("usage: write_tiny_ggufs DIR")?;
    let dir = std::path::Path::new(&dir);
    std::fs::create_dir_all(dir)?;
    for f in [Family::Llama, Family::Qwen2, Family::Qwen3, Family::Gemma3] {
        let p = dir.join(format!("tiny-{}.gguf", f.name()));
        tiny_gguf::write(f, &p, tiny_gguf::PARITY_SEED, true)?;
        println!("{} {}", p.display(), tiny_gguf::fingerprint(&p)?);
    }
    Ok(())
}
