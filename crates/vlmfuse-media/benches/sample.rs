//! Frame sampling cost on a dashcam-sized clip (20 s, 1280x720, 30 fps, H.264), against
//! decoding every frame and against the `ffmpeg` CLI extracting the same frames.
//!
//! Run with `cargo bench -p vlmfuse-media --bench sample`. Every method produces the same
//! output: N native-size RGB24 frames, the first frame at or after each target time.

use std::path::Path;
use std::time::{Duration, Instant};

use vlmfuse_media::{
    sample_frames_with_policy, target_times, DecodePolicy, DecodeStats, FrameSize, MediaLimits,
    SampleOptions,
};

use vlmfuse_testkit::clips::ffmpeg;

const REPEATS: usize = 3;

fn make_clip(path: &Path, gop: Option<u32>) {
    let mut args: Vec<String> = [
        "-f",
        "lavfi",
        "-i",
        "testsrc2=size=1280x720:rate=30:duration=20,hue=H=2*PI*t/3",
        "-c:v",
        "libx264",
        "-preset",
        "ultrafast",
        "-pix_fmt",
        "yuv420p",
    ]
    .map(String::from)
    .to_vec();
    if let Some(g) = gop {
        args.extend(["-g".to_string(), g.to_string()]);
    }
    args.push(path.display().to_string());
    ffmpeg(&args);
}

/// Median wall time of `REPEATS` runs (after one warm-up run that fills the page cache).
fn time<T>(mut f: impl FnMut() -> T) -> (Duration, T) {
    let mut out = f();
    let mut times = Vec::with_capacity(REPEATS);
    for _ in 0..REPEATS {
        let t = Instant::now();
        out = f();
        times.push(t.elapsed());
    }
    times.sort();
    (times[REPEATS / 2], out)
}

/// The fast CLI way: one process, one input per target with input seeking (`-ss` before `-i`
/// seeks to the keyframe before the target and decodes up to it exactly), one raw RGB frame
/// out per input.
fn cli_multi_seek(clip: &Path, targets: &[f64], out_dir: &Path) {
    let mut args = Vec::new();
    for t in targets {
        args.extend([
            "-ss".to_string(),
            format!("{t:.6}"),
            "-i".into(),
            clip.display().to_string(),
        ]);
    }
    for j in 0..targets.len() {
        args.extend([
            "-map".to_string(),
            format!("{j}:v:0"),
            "-frames:v".into(),
            "1".into(),
            "-f".into(),
            "rawvideo".into(),
            "-pix_fmt".into(),
            "rgb24".into(),
            out_dir.join(format!("cli{j}.rgb")).display().to_string(),
        ]);
    }
    ffmpeg(&args);
}

/// The other common CLI way: decode the whole clip once and keep the frames a `select`
/// filter picks.
fn cli_select(clip: &Path, targets: &[f64], out_dir: &Path) {
    // First frame at or after each target, on a 30 fps grid.
    let expr = targets
        .iter()
        .map(|t| format!("eq(n\\,{})", (t * 30.0 - 1e-6).ceil() as u64))
        .collect::<Vec<_>>()
        .join("+");
    ffmpeg(&[
        "-i".into(),
        clip.display().to_string(),
        "-vf".into(),
        format!("select='{expr}'"),
        "-vsync".into(),
        "0".into(),
        "-f".into(),
        "rawvideo".into(),
        "-pix_fmt".into(),
        "rgb24".into(),
        out_dir.join("select.rgb").display().to_string(),
    ]);
}

fn main() {
    let dir = tempfile::tempdir().expect("tempdir");
    let clips = [
        ("kf 1 s (-g 30)", dir.path().join("g30.mp4"), Some(30)),
        ("kf 8.3 s (default)", dir.path().join("gdef.mp4"), None),
    ];
    for (_, path, gop) in &clips {
        make_clip(path, *gop);
    }
    let limits = MediaLimits::default();

    println!(
        "\n{:<19} {:<30} {:>3} {:>9} {:>8} {:>7} {:>6}",
        "clip", "method", "N", "ms", "vs CLI", "frames", "seeks"
    );
    for (label, path, _) in &clips {
        for n in [8usize, 16] {
            let opts = SampleOptions {
                frames: n,
                size: FrameSize::Native,
            };
            let sample =
                |policy| sample_frames_with_policy(path, &opts, &limits, policy).expect("sampling");
            let (cli_ms, ()) = time(|| cli_multi_seek(path, &target_times(20.0, n), dir.path()));
            let cli = cli_ms.as_secs_f64() * 1e3;

            // Sanity: the CLI picked the same frames (same pixels, up to colour conversion).
            let (clip, _) = sample(DecodePolicy::Auto);
            let mut worst = 0.0f64;
            for (j, f) in clip.frames.iter().enumerate() {
                let raw = std::fs::read(dir.path().join(format!("cli{j}.rgb"))).unwrap();
                assert_eq!(raw.len(), f.rgb.len(), "CLI frame {j} has another size");
                let mad = raw
                    .iter()
                    .zip(&f.rgb)
                    .map(|(&a, &b)| f64::from(a.abs_diff(b)))
                    .sum::<f64>()
                    / raw.len() as f64;
                worst = worst.max(mad);
            }

            let mut rows: Vec<(&str, f64, Option<DecodeStats>)> = Vec::new();
            for (name, policy) in [
                ("sample_frames (auto)", DecodePolicy::Auto),
                ("  forced: decode forward", DecodePolicy::Forward),
                ("  forced: seek every target", DecodePolicy::Seek),
                ("(a) decode every frame", DecodePolicy::Everything),
            ] {
                let (d, (_, stats)) = time(|| sample(policy));
                rows.push((name, d.as_secs_f64() * 1e3, Some(stats)));
            }
            rows.push(("(b) ffmpeg CLI, -ss per frame", cli, None));
            let (sel, ()) = time(|| cli_select(path, &target_times(20.0, n), dir.path()));
            rows.push((
                "    ffmpeg CLI, select filter",
                sel.as_secs_f64() * 1e3,
                None,
            ));

            for (name, ms, stats) in rows {
                let (frames, seeks) = stats.map_or((String::new(), String::new()), |s| {
                    (s.frames_decoded.to_string(), s.seeks.to_string())
                });
                println!(
                    "{label:<19} {name:<30} {n:>3} {ms:>9.1} {:>7.2}x {frames:>7} {seeks:>6}",
                    ms / cli
                );
            }
            println!("{label:<19} (max mean |ours - CLI| per frame: {worst:.2} / 255)");
        }
    }

    // FFmpeg's frame threads against one thread per clip (`MediaLimits::decode_threads`), on
    // the paper's clip shape, at the native size and at the service's default short side.
    let (_, g30, _) = &clips[0];
    println!(
        "\n{:<26} {:>3} {:>9} {:>9}",
        "decode_threads (kf 1 s)", "N", "native", "short 448"
    );
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    let mut base = None;
    for threads in [1usize, 2, 4, 0] {
        let limits = MediaLimits {
            decode_threads: threads,
            ..MediaLimits::default()
        };
        let ms = |size| {
            let opts = SampleOptions { frames: 8, size };
            let (d, _) = time(|| {
                sample_frames_with_policy(g30, &opts, &limits, DecodePolicy::Auto)
                    .expect("sampling")
            });
            d.as_secs_f64() * 1e3
        };
        let (native, short) = (ms(FrameSize::Native), ms(FrameSize::ShortSide(448)));
        let b = *base.get_or_insert(native);
        let name = match threads {
            0 => format!("0 (auto: {} here)", cores.min(8)),
            n => n.to_string(),
        };
        println!(
            "{name:<26} {:>3} {native:>9.1} {short:>9.1}   ({:.2}x of 1 thread)",
            8,
            native / b
        );
    }
}
