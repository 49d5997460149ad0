//! Test clips, made at test time with the `ffmpeg` CLI (no footage is committed).

use std::path::{Path, PathBuf};
use std::process::Command;

/// Runs `ffmpeg -y <args>` quietly and panics with its stderr on failure.
pub fn ffmpeg<S: AsRef<std::ffi::OsStr>>(args: &[S]) {
    let out = Command::new("ffmpeg")
        .args(["-hide_banner", "-loglevel", "error", "-nostdin", "-y"])
        .args(args)
        .output()
        .expect("the ffmpeg CLI must be installed (scripts/setup-system.sh)");
    assert!(
        out.status.success(),
        "ffmpeg {:?} failed: {}",
        args.iter().map(|a| a.as_ref()).collect::<Vec<_>>(),
        String::from_utf8_lossy(&out.stderr)
    );
}

/// `ffmpeg <args> <out>`: returns `out`.
pub fn ffmpeg_to(args: &[&str], out: &Path) -> PathBuf {
    let mut all: Vec<&std::ffi::OsStr> = args.iter().map(|a| a.as_ref()).collect();
    all.push(out.as_os_str());
    ffmpeg(&all);
    out.to_path_buf()
}

/// A short 160x120 H.264 mp4 of an lavfi source (`testsrc`, `mandelbrot`, ...).
pub fn h264_clip(dir: &Path, name: &str, source: &str, secs: f64) -> PathBuf {
    ffmpeg_to(
        &[
            "-f",
            "lavfi",
            "-i",
            &format!("{source}=size=160x120:rate=10"),
            "-t",
            &secs.to_string(),
            "-c:v",
            "libx264",
            "-pix_fmt",
            "yuv420p",
        ],
        &dir.join(name),
    )
}
