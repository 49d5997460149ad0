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

/// The offset of the first ISO-BMFF box along `path` (`moov`, `trak`, ...) in an MP4's bytes,
/// walking from the top; `None` when there is none or a size on the way is inconsistent. Tests
/// use it to rewrite one field of a real clip (a sample count) into a hostile file.
pub fn mp4_box(data: &[u8], path: &[&[u8; 4]]) -> Option<usize> {
    fn walk(data: &[u8], start: usize, end: usize, path: &[&[u8; 4]]) -> Option<usize> {
        let mut at = start;
        while at + 8 <= end {
            let size = u32::from_be_bytes(data[at..at + 4].try_into().ok()?) as usize;
            // Size 0: the box runs to the end of its parent.
            let size = if size == 0 { end - at } else { size };
            if size < 8 || at + size > end {
                return None;
            }
            if &data[at + 4..at + 8] == path[0] {
                if path.len() == 1 {
                    return Some(at);
                }
                if let Some(found) = walk(data, at + 8, at + size, &path[1..]) {
                    return Some(found);
                }
            }
            at += size;
        }
        None
    }
    if path.is_empty() {
        return None;
    }
    walk(data, 0, data.len(), path)
}
