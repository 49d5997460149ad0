//! Checks a directory that `scripts/parity/yolo_detect.py --out DIR` wrote (for example the real
//! YOLO11n at 640, whose ~10 MB ONNX is never committed) against this crate, and prints what
//! differed: preprocessing, decoding + NMS from the stored raw outputs, and the whole ONNX path.
//!
//!     cargo run --release -p vlmfuse-detect --example parity -- DIR
//!
//! The committed tiny model's directory is checked by `tests/parity.rs`; this is the same
//! comparison as a measurement.

#[path = "../tests/support/parity.rs"]
mod parity;

fn main() {
    let dir = std::env::args()
        .nth(1)
        .map(std::path::PathBuf::from)
        .unwrap_or_else(parity::committed);
    let pure = parity::check_pure(&dir);
    println!("decode + NMS from ultralytics' raw outputs: {pure:#?}");
    let onnx = parity::check_onnx(&dir);
    println!("ONNX Runtime path: {onnx:#?}");
    if dir.join("tracker.json").is_file() {
        println!("trackers: {:#?}", parity::check_tracker(&dir));
    }
    let ok = pure.max_grey_diff <= 1
        && pure.kept_set_mismatches.is_empty()
        && onnx.kept_set_mismatches.is_empty()
        && pure.max_box_diff <= 1e-3
        && onnx.max_box_diff <= 1e-3;
    println!("{}", if ok { "PARITY OK" } else { "PARITY FAILED" });
    if !ok {
        std::process::exit(1);
    }
}
