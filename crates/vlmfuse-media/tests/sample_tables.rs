//! MP4s whose sample tables declare millions of samples in a few KB: FFmpeg's mov demuxer
//! allocates for every declared entry, so they must be refused before it opens them. Each
//! hostile file is a real clip made at test time with its counts rewritten.

mod common;

use std::path::{Path, PathBuf};

use common::{ffmpeg, h264, make_clip};
use vlmfuse_media::{probe, sample_frames, MediaError, MediaLimits, SampleOptions};

/// The offset of the first box along `path` (`moov`, `trak`, ...), walking from the top.
fn find_box(data: &[u8], path: &[&[u8; 4]]) -> usize {
    vlmfuse_testkit::clips::mp4_box(data, path).unwrap_or_else(|| panic!("no box {path:?}"))
}

fn put32(data: &mut [u8], at: usize, v: u32) {
    data[at..at + 4].copy_from_slice(&v.to_be_bytes());
}

const STBL: [&[u8; 4]; 5] = [b"moov", b"trak", b"mdia", b"minf", b"stbl"];

fn stbl_box(data: &[u8], name: &'static [u8; 4]) -> usize {
    let mut path = STBL.to_vec();
    path.push(name);
    find_box(data, &path)
}

/// A 2 s, 160x120 H.264 mp4 (20 samples).
fn clip(dir: &Path, name: &str, extra: &[&'static str]) -> PathBuf {
    make_clip(dir, name, (160, 120, 10, 2.0), &h264(extra))
}

/// Writes `clip` with `edit` applied to its bytes as `name`.
fn rewrite(clip: &Path, name: &str, edit: impl FnOnce(&mut Vec<u8>)) -> PathBuf {
    let mut data = std::fs::read(clip).unwrap();
    edit(&mut data);
    let out = clip.with_file_name(name);
    std::fs::write(&out, data).unwrap();
    out
}

/// Probing and sampling both refuse `path` with [`MediaError::TooManySamples`] from `table`;
/// returns the declared count.
fn too_many_samples(path: &Path, table: &str) -> u64 {
    let limits = MediaLimits::default();
    let p = probe(path, &limits);
    let s = sample_frames(path, &SampleOptions::default(), &limits);
    let mut declared = 0;
    for r in [p.map(drop), s.map(drop)] {
        match r {
            Err(MediaError::TooManySamples {
                table: t,
                declared: d,
                limit,
            }) => {
                assert_eq!(t, table, "{}", path.display());
                assert!(d > limit, "{d} <= {limit}");
                declared = d;
            }
            other => panic!("{}: {other:?}", path.display()),
        }
    }
    let e = probe(path, &limits).unwrap_err();
    assert_eq!(e.kind(), "too_many_samples");
    assert!(e.is_client_error());
    declared
}

#[test]
fn per_sample_sizes_that_the_file_does_not_hold_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let ok = clip(dir.path(), "ok.mp4", &[]);
    let bad = rewrite(&ok, "stsz.mp4", |d| {
        let stsz = stbl_box(d, b"stsz");
        assert_eq!(&d[stsz + 12..stsz + 16], &[0; 4], "per-sample sizes");
        put32(d, stsz + 16, 50_000_000);
    });
    assert_eq!(too_many_samples(&bad, "stsz"), 50_000_000);
    // The timing and chunk tables are checked the same way.
    for (table, count_at) in [(b"stts", 12), (b"stsc", 12), (b"stco", 12)] {
        let name = std::str::from_utf8(table).unwrap();
        let bad = rewrite(&ok, &format!("{name}.mp4"), |d| {
            let at = stbl_box(d, table);
            put32(d, at + count_at, 80_000_000);
        });
        assert_eq!(too_many_samples(&bad, name), 80_000_000);
    }
}

#[test]
fn millions_of_samples_of_one_constant_size_are_refused() {
    // A constant sample size declares any number of samples in 20 bytes; FFmpeg would build an
    // index entry for each.
    let dir = tempfile::tempdir().unwrap();
    let ok = clip(dir.path(), "ok.mp4", &[]);
    let bad = rewrite(&ok, "constant.mp4", |d| {
        let stsz = stbl_box(d, b"stsz");
        put32(d, stsz + 12, 1000);
        put32(d, stsz + 16, 40_000_000);
    });
    assert_eq!(too_many_samples(&bad, "stsz"), 40_000_000);
}

#[test]
fn a_fragment_declaring_millions_of_samples_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let ok = clip(
        dir.path(),
        "frag.mp4",
        &["-movflags", "+frag_keyframe+empty_moov"],
    );
    sample_frames(&ok, &SampleOptions::default(), &MediaLimits::default())
        .expect("the fragmented clip itself samples");
    let bad = rewrite(&ok, "trun.mp4", |d| {
        let trun = find_box(d, &[b"moof", b"traf", b"trun"]);
        // No per-sample fields: the samples cost no bytes of the file.
        let flags = u32::from_be_bytes(d[trun + 8..trun + 12].try_into().unwrap());
        put32(d, trun + 8, flags & !0xf00);
        put32(d, trun + 12, 20_000_000);
    });
    assert_eq!(too_many_samples(&bad, "trun"), 20_000_000);
}

#[test]
fn an_index_box_overrunning_its_parent_is_corrupt() {
    let dir = tempfile::tempdir().unwrap();
    let ok = clip(dir.path(), "ok.mp4", &["-movflags", "+faststart"]);
    let bad = rewrite(&ok, "overrun.mp4", |d| {
        let stsz = stbl_box(d, b"stsz");
        put32(d, stsz, 1 << 30);
    });
    for r in [
        probe(&bad, &MediaLimits::default()).map(drop),
        sample_frames(&bad, &SampleOptions::default(), &MediaLimits::default()).map(drop),
    ] {
        match r {
            Err(MediaError::Corrupt(m)) => assert!(m.contains("stsz"), "{m}"),
            other => panic!("{other:?}"),
        }
    }
}

/// Ten seconds of 48 kHz PCM declare 480,000 samples, four times the sample limit, but FFmpeg
/// indexes uncompressed audio by chunk: such a clip is ordinary and must still open.
#[test]
fn uncompressed_audio_beside_the_video_still_opens() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("pcm.mov");
    ffmpeg(&[
        "-f",
        "lavfi",
        "-i",
        "testsrc2=size=160x120:rate=10:duration=10",
        "-f",
        "lavfi",
        "-i",
        "sine=frequency=440:sample_rate=48000:duration=10",
        "-c:v",
        "libx264",
        "-preset",
        "ultrafast",
        "-pix_fmt",
        "yuv420p",
        "-c:a",
        "pcm_s16le",
        p.to_str().unwrap(),
    ]);
    let data = std::fs::read(&p).unwrap();
    // The audio track (the second) declares its PCM samples one by one.
    let audio = {
        let first = find_box(&data, &[b"moov", b"trak"]);
        let len = u32::from_be_bytes(data[first..first + 4].try_into().unwrap()) as usize;
        let rest = &data[first + len..];
        let stsz = rest.windows(4).position(|w| w == b"stsz").unwrap() - 4;
        u32::from_be_bytes(rest[stsz + 16..stsz + 20].try_into().unwrap())
    };
    assert!(audio >= 480_000, "{audio}");
    let clip = sample_frames(&p, &SampleOptions::default(), &MediaLimits::default()).unwrap();
    assert_eq!(clip.frames.len(), 8);
    assert!((clip.info.duration_s - 10.0).abs() < 0.2, "{:?}", clip.info);
}
