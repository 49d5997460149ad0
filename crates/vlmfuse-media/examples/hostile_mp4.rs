//! Measures what an MP4 declaring millions of samples costs to refuse: peak RSS growth and
//! time to the answer of one `sample_frames` call.
//!
//! ```text
//! cargo run -p vlmfuse-media --example hostile_mp4 -- make DIR      # writes DIR/*.mp4
//! cargo run -p vlmfuse-media --example hostile_mp4 -- run FILE      # one measurement
//! ```
//!
//! Run each file in its own process: the peak (`VmHWM`) only ever grows.

use std::path::Path;
use std::time::Instant;

use vlmfuse_media::{sample_frames, MediaLimits, SampleOptions};

use vlmfuse_testkit::clips::mp4_box;

fn status_kb(field: &str) -> u64 {
    let s = std::fs::read_to_string("/proc/self/status").unwrap();
    s.lines()
        .find_map(|l| l.strip_prefix(field))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse().ok())
        .unwrap_or(0)
}

fn put32(d: &mut [u8], at: usize, v: u32) {
    d[at..at + 4].copy_from_slice(&v.to_be_bytes());
}

fn make(dir: &Path) {
    std::fs::create_dir_all(dir).unwrap();
    // 1 s of 16x16 at 10 fps: a file of about 3 KB, like the report's.
    let ok = vlmfuse_testkit::clips::ffmpeg_to(
        &[
            "-f",
            "lavfi",
            "-i",
            "color=c=red:size=16x16:rate=10:duration=1",
            "-c:v",
            "libx264",
            "-preset",
            "ultrafast",
            "-pix_fmt",
            "yuv420p",
            "-movflags",
            "+faststart",
        ],
        &dir.join("ok.mp4"),
    );
    let data = std::fs::read(&ok).unwrap();
    let stsz = mp4_box(
        &data,
        &[b"moov", b"trak", b"mdia", b"minf", b"stbl", b"stsz"],
    )
    .unwrap();
    for (name, size, count) in [
        ("sizes-10M.mp4", 0, 10_000_000),
        ("constant-80M.mp4", 1000, 80_000_000),
    ] {
        let mut d = data.clone();
        put32(&mut d, stsz + 12, size);
        put32(&mut d, stsz + 16, count);
        std::fs::write(dir.join(name), &d).unwrap();
        println!("{name}: {} bytes", d.len());
    }
    // The report's shape: the whole index agrees on 80 million samples of 1000 bytes in one
    // chunk (constant size, one stsc run, one stts run), so FFmpeg fills an index entry for
    // every one of them.
    let mut d = data.clone();
    let stbl = [b"moov", b"trak", b"mdia", b"minf", b"stbl"];
    let at = |d: &[u8], name: &'static [u8; 4]| {
        let mut p: Vec<&[u8; 4]> = stbl.to_vec();
        p.push(name);
        mp4_box(d, &p).unwrap()
    };
    let (stsz, stsc, stts) = (at(&d, b"stsz"), at(&d, b"stsc"), at(&d, b"stts"));
    put32(&mut d, stsz + 12, 1000);
    put32(&mut d, stsz + 16, 80_000_000);
    put32(&mut d, stsc + 12, 1);
    put32(&mut d, stsc + 20, 80_000_000);
    put32(&mut d, stts + 12, 1);
    put32(&mut d, stts + 16, 80_000_000);
    std::fs::write(dir.join("index-80M.mp4"), &d).unwrap();
    println!("index-80M.mp4: {} bytes", d.len());
    // A fragmented clip whose first `trun` declares 20 million samples and no per-sample
    // fields (so the samples cost no bytes).
    let frag = vlmfuse_testkit::clips::ffmpeg_to(
        &[
            "-f",
            "lavfi",
            "-i",
            "color=c=red:size=16x16:rate=10:duration=1",
            "-c:v",
            "libx264",
            "-preset",
            "ultrafast",
            "-pix_fmt",
            "yuv420p",
            "-movflags",
            "+frag_keyframe+empty_moov",
        ],
        &dir.join("frag.mp4"),
    );
    let mut d = std::fs::read(&frag).unwrap();
    let trun = mp4_box(&d, &[b"moof", b"traf", b"trun"]).unwrap();
    let flags = u32::from_be_bytes(d[trun + 8..trun + 12].try_into().unwrap());
    put32(&mut d, trun + 8, flags & !0xf00);
    put32(&mut d, trun + 12, 20_000_000);
    std::fs::write(dir.join("trun-20M.mp4"), &d).unwrap();
    println!("trun-20M.mp4: {} bytes", d.len());
}

fn run(path: &Path) {
    let (hwm0, rss0) = (status_kb("VmHWM:"), status_kb("VmRSS:"));
    let t = Instant::now();
    let r = sample_frames(path, &SampleOptions::default(), &MediaLimits::default());
    let secs = t.elapsed().as_secs_f64();
    let hwm1 = status_kb("VmHWM:");
    let outcome = match r {
        Ok(c) => format!("sampled {} frames", c.frames.len()),
        Err(e) => format!("refused: {} ({e})", e.kind()),
    };
    println!(
        "{}: {outcome}; {secs:.3} s; peak RSS {} -> {} MB (growth {} MB; RSS before {} MB)",
        path.display(),
        hwm0 / 1024,
        hwm1 / 1024,
        hwm1.saturating_sub(hwm0) / 1024,
        rss0 / 1024
    );
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    match (args.get(1).map(String::as_str), args.get(2)) {
        (Some("make"), Some(dir)) => make(Path::new(dir)),
        (Some("run"), Some(file)) => run(Path::new(file)),
        _ => eprintln!("usage: hostile_mp4 make DIR | run FILE"),
    }
}
