//! What the parity tests share: reading the reference outputs the scripts under
//! `scripts/parity/` wrote (floats as base64 of little-endian f32) and comparing floats.

use std::path::{Path, PathBuf};

use base64::Engine;

/// `tests/data/parity/<family>/` of the repository.
pub fn data_dir(family: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../tests/data/parity")
        .join(family)
}

/// A reference JSON file; a missing one names the script that writes it.
pub fn read_reference(family: &str, name: &str, script: &str) -> serde_json::Value {
    let p = data_dir(family).join(name);
    let text = std::fs::read_to_string(&p)
        .unwrap_or_else(|e| panic!("{}: {e} (run {script} to create it)", p.display()));
    serde_json::from_str(&text).unwrap()
}

/// The bytes of a base64 string.
pub fn b64(v: &serde_json::Value) -> Vec<u8> {
    base64::engine::general_purpose::STANDARD
        .decode(v.as_str().expect("base64 string"))
        .unwrap()
}

/// The f32s of a base64 string of little-endian floats.
pub fn f32s(v: &serde_json::Value) -> Vec<f32> {
    b64(v)
        .chunks_exact(4)
        .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect()
}

/// The largest absolute difference of two equally long slices.
pub fn max_abs_diff(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len());
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max)
}
