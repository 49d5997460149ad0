//! Test clips, made at test time with the `ffmpeg` CLI from lavfi sources.

#![allow(dead_code)]

use std::path::{Path, PathBuf};

use vlmfuse_media::Frame;

pub use vlmfuse_testkit::clips::ffmpeg;

/// A moving test pattern whose colours also rotate over time, so frames a fraction of a
/// second apart differ everywhere, not only in a few moving pixels.
pub fn source(width: u32, height: u32, fps: u32, seconds: f64) -> String {
    format!("testsrc2=size={width}x{height}:rate={fps}:duration={seconds},hue=H=2*PI*t/3")
}

/// Encodes the moving pattern into `dir/name` with the given codec arguments.
pub fn make_clip(
    dir: &Path,
    name: &str,
    (width, height, fps, seconds): (u32, u32, u32, f64),
    codec_args: &[&str],
) -> PathBuf {
    let path = dir.join(name);
    let src = source(width, height, fps, seconds);
    let mut args = vec!["-f", "lavfi", "-i", &src];
    args.extend_from_slice(codec_args);
    let p = path.to_str().expect("utf-8 temp path");
    args.push(p);
    ffmpeg(&args);
    path
}

pub fn h264(extra: &[&'static str]) -> Vec<&'static str> {
    let mut v = vec![
        "-c:v",
        "libx264",
        "-preset",
        "ultrafast",
        "-pix_fmt",
        "yuv420p",
    ];
    v.extend_from_slice(extra);
    v
}

/// Mean absolute difference of two equally sized RGB frames, 0..255.
pub fn mean_abs_diff(a: &Frame, b: &Frame) -> f64 {
    assert_eq!(a.rgb.len(), b.rgb.len(), "frames of different sizes");
    let sum: u64 = a
        .rgb
        .iter()
        .zip(&b.rgb)
        .map(|(&x, &y)| u64::from(x.abs_diff(y)))
        .sum();
    sum as f64 / a.rgb.len().max(1) as f64
}
