//! Sampling over the containers and codecs users upload, checked against the naive
//! decode-everything path.

mod common;

use std::path::Path;
use std::time::Instant;

use common::{h264, make_clip, mean_abs_diff};
use vlmfuse_media::{
    probe, sample_frames, sample_frames_with_policy, target_times, DecodePolicy, FrameSize,
    MediaLimits, SampleOptions,
};

struct Expect {
    container: &'static str,
    codec: &'static str,
    width: u32,
    height: u32,
    fps: f64,
    seconds: f64,
}

/// Probes and samples `path` and checks everything a caller relies on.
fn check_clip(path: &Path, e: &Expect, n: usize) {
    let limits = MediaLimits::default();
    let info = probe(path, &limits).expect("probe");
    assert_eq!(info.container, e.container, "{info:?}");
    assert_eq!(info.codec, e.codec, "{info:?}");
    assert_eq!((info.width, info.height), (e.width, e.height));
    assert!((info.fps - e.fps).abs() < 0.01, "fps {info:?}");
    // Containers round the duration to their own clock; a frame of slack is enough.
    assert!(
        (info.duration_s - e.seconds).abs() <= 1.5 / e.fps + 0.01,
        "duration {info:?}"
    );

    let opts = SampleOptions {
        frames: n,
        size: FrameSize::Native,
    };
    let clip = sample_frames(path, &opts, &limits).expect("sample");
    assert_eq!(clip.info, info);
    assert_eq!(clip.frames.len(), n);
    let targets = target_times(info.duration_s, n);
    let ts = clip.timestamps();
    for (j, f) in clip.frames.iter().enumerate() {
        assert_eq!(f.index, j);
        assert!((f.target_s - targets[j]).abs() < 1e-9);
        // The first frame at or after the target: at most one frame period later.
        assert!(
            f.pts_s >= f.target_s - 1e-6 && f.pts_s - f.target_s <= 1.0 / e.fps + 1e-3,
            "{}: frame {j} at {} for target {} ({ts:?})",
            path.display(),
            f.pts_s,
            f.target_s
        );
        assert_eq!((f.width, f.height), (e.width, e.height));
        assert_eq!(f.rgb.len(), (e.width * e.height * 3) as usize);
    }
    assert!(
        ts.windows(2).all(|w| w[1] > w[0]),
        "timestamps not increasing: {ts:?}"
    );
    for w in clip.frames.windows(2) {
        let d = mean_abs_diff(&w[0], &w[1]);
        assert!(
            d > 3.0,
            "{}: frames at {} and {} barely differ ({d:.2})",
            path.display(),
            w[0].pts_s,
            w[1].pts_s
        );
    }

    // Deterministic, and every decoding strategy returns the very same frames.
    let again = sample_frames(path, &opts, &limits).expect("sample again");
    assert!(again == clip, "{}: second sampling differs", path.display());
    let (naive, naive_stats) =
        sample_frames_with_policy(path, &opts, &limits, DecodePolicy::Everything).unwrap();
    for policy in [DecodePolicy::Forward, DecodePolicy::Seek] {
        let (other, _) = sample_frames_with_policy(path, &opts, &limits, policy).unwrap();
        assert_eq!(other.timestamps(), naive.timestamps(), "{policy:?}");
        assert!(
            other == naive,
            "{}: {policy:?} frames differ",
            path.display()
        );
    }
    assert_eq!(clip.timestamps(), naive.timestamps());
    assert!(
        clip == naive,
        "{}: Auto frames differ from Everything",
        path.display()
    );
    let expected_frames = (e.seconds * e.fps).round() as u64;
    assert_eq!(
        naive_stats.frames_decoded, expected_frames,
        "{naive_stats:?}"
    );
}

#[test]
fn mp4_h264() {
    let dir = tempfile::tempdir().unwrap();
    let p = make_clip(
        dir.path(),
        "a.mp4",
        (320, 240, 25, 4.0),
        &h264(&["-g", "25"]),
    );
    let e = Expect {
        container: "mp4",
        codec: "h264",
        width: 320,
        height: 240,
        fps: 25.0,
        seconds: 4.0,
    };
    check_clip(&p, &e, 8);
    check_clip(&p, &e, 5);
    let info = probe(&p, &MediaLimits::default()).unwrap();
    let k = info.keyframe_interval_s.expect("mp4 has an index");
    assert!((k - 1.0).abs() < 0.05, "keyframe interval {k}");
}

#[test]
fn mp4_h264_with_b_frames_and_audio() {
    // B-frames reorder pts against dts, and an audio track interleaves packets.
    let dir = tempfile::tempdir().unwrap();
    let p = make_clip(
        dir.path(),
        "b.mp4",
        (256, 144, 30, 3.0),
        &[
            "-f",
            "lavfi",
            "-i",
            "sine=frequency=440:duration=3",
            "-c:v",
            "libx264",
            "-preset",
            "veryfast",
            "-bf",
            "3",
            "-g",
            "15",
            "-pix_fmt",
            "yuv420p",
            "-c:a",
            "aac",
            "-shortest",
        ],
    );
    let e = Expect {
        container: "mp4",
        codec: "h264",
        width: 256,
        height: 144,
        fps: 30.0,
        seconds: 3.0,
    };
    check_clip(&p, &e, 8);
    check_clip(&p, &e, 16);
}

#[test]
fn mov_h264() {
    let dir = tempfile::tempdir().unwrap();
    let p = make_clip(dir.path(), "a.mov", (240, 180, 24, 2.5), &h264(&[]));
    let e = Expect {
        container: "mov",
        codec: "h264",
        width: 240,
        height: 180,
        fps: 24.0,
        seconds: 2.5,
    };
    check_clip(&p, &e, 8);
}

#[test]
fn mkv_h264_10fps() {
    let dir = tempfile::tempdir().unwrap();
    let p = make_clip(
        dir.path(),
        "a.mkv",
        (320, 180, 10, 6.0),
        &h264(&["-g", "5"]),
    );
    let e = Expect {
        container: "matroska",
        codec: "h264",
        width: 320,
        height: 180,
        fps: 10.0,
        seconds: 6.0,
    };
    check_clip(&p, &e, 8);
    check_clip(&p, &e, 12);
}

#[test]
fn avi_mpeg4() {
    let dir = tempfile::tempdir().unwrap();
    let p = make_clip(
        dir.path(),
        "a.avi",
        (176, 144, 15, 3.0),
        &["-c:v", "mpeg4", "-q:v", "5", "-g", "10"],
    );
    let e = Expect {
        container: "avi",
        codec: "mpeg4",
        width: 176,
        height: 144,
        fps: 15.0,
        seconds: 3.0,
    };
    check_clip(&p, &e, 8);
}

#[test]
fn avi_mjpeg() {
    let dir = tempfile::tempdir().unwrap();
    let p = make_clip(
        dir.path(),
        "m.avi",
        (160, 120, 20, 2.0),
        &["-c:v", "mjpeg", "-q:v", "4", "-pix_fmt", "yuvj420p"],
    );
    let e = Expect {
        container: "avi",
        codec: "mjpeg",
        width: 160,
        height: 120,
        fps: 20.0,
        seconds: 2.0,
    };
    check_clip(&p, &e, 8);
    let info = probe(&p, &MediaLimits::default()).unwrap();
    assert!(
        (info.keyframe_interval_s.unwrap() - 0.05).abs() < 1e-6,
        "{info:?}"
    );
}

#[test]
fn webm_vp9_and_vp8() {
    let dir = tempfile::tempdir().unwrap();
    let vp9 = make_clip(
        dir.path(),
        "a.webm",
        (192, 108, 25, 2.0),
        &[
            "-c:v",
            "libvpx-vp9",
            "-deadline",
            "realtime",
            "-cpu-used",
            "8",
            "-g",
            "10",
        ],
    );
    let vp8 = make_clip(
        dir.path(),
        "b.webm",
        (192, 108, 30, 2.0),
        &[
            "-c:v",
            "libvpx",
            "-deadline",
            "realtime",
            "-cpu-used",
            "8",
            "-b:v",
            "1M",
        ],
    );
    let mut e = Expect {
        container: "webm",
        codec: "vp9",
        width: 192,
        height: 108,
        fps: 25.0,
        seconds: 2.0,
    };
    check_clip(&vp9, &e, 8);
    e.codec = "vp8";
    e.fps = 30.0;
    check_clip(&vp8, &e, 8);
}

#[test]
fn sixty_fps_and_very_short_clips() {
    let dir = tempfile::tempdir().unwrap();
    let p = make_clip(dir.path(), "60.mp4", (160, 90, 60, 1.0), &h264(&[]));
    let e = Expect {
        container: "mp4",
        codec: "h264",
        width: 160,
        height: 90,
        fps: 60.0,
        seconds: 1.0,
    };
    check_clip(&p, &e, 16);

    // Fewer frames than targets (5 frames at 0.0, 0.1, ... 0.4 s): frames repeat, and each
    // target gets the first frame at or after it, or the last frame past the end.
    let short = make_clip(dir.path(), "s.mp4", (160, 90, 10, 0.5), &h264(&[]));
    let opts = SampleOptions {
        frames: 8,
        size: FrameSize::Native,
    };
    let clip = sample_frames(&short, &opts, &MediaLimits::default()).unwrap();
    let ts = clip.timestamps();
    let expected: Vec<f64> = target_times(0.5, 8)
        .iter()
        .map(|&t| ((t * 10.0).ceil() / 10.0).min(0.4))
        .collect();
    assert_eq!(ts.len(), expected.len());
    for (got, want) in ts.iter().zip(&expected) {
        assert!((got - want).abs() < 1e-6, "{ts:?} != {expected:?}");
    }
    assert_ne!(clip.frames[0].rgb, clip.frames[7].rgb);
    assert_eq!(clip.frames[6].rgb, clip.frames[7].rgb);
}

#[test]
fn frame_size_modes() {
    let dir = tempfile::tempdir().unwrap();
    let land = make_clip(dir.path(), "l.mp4", (320, 180, 25, 1.0), &h264(&[]));
    let port = make_clip(dir.path(), "p.mp4", (180, 320, 25, 1.0), &h264(&[]));
    let limits = MediaLimits::default();
    let cases = [
        (&land, FrameSize::Native, (320, 180)),
        (&land, FrameSize::ShortSide(90), (160, 90)),
        (&land, FrameSize::ShortSide(224), (398, 224)),
        (&port, FrameSize::ShortSide(224), (224, 398)),
        (
            &land,
            FrameSize::Exact {
                width: 64,
                height: 48,
            },
            (64, 48),
        ),
        (
            &port,
            FrameSize::Exact {
                width: 336,
                height: 336,
            },
            (336, 336),
        ),
    ];
    for (path, size, (w, h)) in cases {
        let clip = sample_frames(path, &SampleOptions { frames: 3, size }, &limits).unwrap();
        for f in &clip.frames {
            assert_eq!((f.width, f.height), (w, h), "{size:?}");
            assert_eq!(f.rgb.len(), (w * h * 3) as usize, "{size:?}");
        }
        assert!(
            mean_abs_diff(&clip.frames[0], &clip.frames[2]) > 3.0,
            "{size:?}"
        );
    }

    // A scaled frame is the native frame, smaller: compare block means roughly.
    let native = sample_frames(
        &land,
        &SampleOptions {
            frames: 1,
            size: FrameSize::Native,
        },
        &limits,
    )
    .unwrap();
    let half = sample_frames(
        &land,
        &SampleOptions {
            frames: 1,
            size: FrameSize::ShortSide(90),
        },
        &limits,
    )
    .unwrap();
    let (n, s) = (&native.frames[0], &half.frames[0]);
    let mean = |v: &[u8]| v.iter().map(|&x| f64::from(x)).sum::<f64>() / v.len() as f64;
    assert!((mean(&n.rgb) - mean(&s.rgb)).abs() < 2.0);
    assert!(mean(&n.rgb) > 20.0, "the frame should not be black");
}

#[test]
fn dashcam_sized_clip_decodes_a_fraction_of_the_frames() {
    // The paper's dataset: 20 s of 1280x720 at 30 fps, H.264 with a keyframe every second.
    let dir = tempfile::tempdir().unwrap();
    let p = make_clip(
        dir.path(),
        "dash.mp4",
        (1280, 720, 30, 20.0),
        &h264(&["-g", "30"]),
    );
    let e = Expect {
        container: "mp4",
        codec: "h264",
        width: 1280,
        height: 720,
        fps: 30.0,
        seconds: 20.0,
    };
    let t = Instant::now();
    check_clip(&p, &e, 8);
    eprintln!("20 s 720p clip checked in {:?}", t.elapsed());

    let limits = MediaLimits::default();
    for n in [8usize, 16] {
        let opts = SampleOptions {
            frames: n,
            size: FrameSize::ShortSide(224),
        };
        let (clip, stats) =
            sample_frames_with_policy(&p, &opts, &limits, DecodePolicy::Auto).unwrap();
        assert_eq!(clip.frames.len(), n);
        assert!(clip
            .frames
            .iter()
            .all(|f| (f.width, f.height) == (398, 224)));
        // Seeking to the keyframe before each target leaves about half a GOP per target.
        assert!(stats.seeks >= n as u64 / 2, "{stats:?}");
        assert!(stats.frames_decoded < 600 / 2, "{stats:?}");
    }
}

#[test]
fn one_keyframe_clip_never_seeks() {
    // A short clip with a single keyframe: every seek would land back at the start.
    let dir = tempfile::tempdir().unwrap();
    let p = make_clip(
        dir.path(),
        "one.mp4",
        (320, 180, 30, 3.0),
        &h264(&["-g", "300"]),
    );
    let info = probe(&p, &MediaLimits::default()).unwrap();
    assert_eq!(info.keyframe_interval_s, Some(info.duration_s));
    let opts = SampleOptions::default();
    let (clip, stats) =
        sample_frames_with_policy(&p, &opts, &MediaLimits::default(), DecodePolicy::Auto).unwrap();
    assert_eq!(stats.seeks, 0, "{stats:?}");
    // It stops after the last target instead of decoding to the end.
    let last = clip.frames.last().unwrap().pts_s;
    assert!(
        stats.frames_decoded <= (last * 30.0).round() as u64 + 10,
        "{stats:?}"
    );
}

#[test]
fn mpegts_h264() {
    // No index: keyframes are learnt while decoding, seeks are blind.
    let dir = tempfile::tempdir().unwrap();
    let p = make_clip(
        dir.path(),
        "a.ts",
        (320, 180, 25, 6.0),
        &h264(&["-g", "25", "-bf", "2"]),
    );
    let e = Expect {
        container: "mpegts",
        codec: "h264",
        width: 320,
        height: 180,
        fps: 25.0,
        seconds: 6.0,
    };
    check_clip(&p, &e, 8);
    assert_eq!(
        probe(&p, &MediaLimits::default())
            .unwrap()
            .keyframe_interval_s,
        None
    );
}

#[test]
fn mpegts_with_one_keyframe_still_samples_after_a_blind_seek() {
    // A blind seek into a stream whose only keyframe is the first frame lands where nothing
    // decodes; sampling must fall back to decoding from the start, not call the clip corrupt.
    let dir = tempfile::tempdir().unwrap();
    let p = make_clip(
        dir.path(),
        "one.ts",
        (160, 90, 30, 8.0),
        &h264(&["-g", "100000", "-sc_threshold", "0"]),
    );
    let e = Expect {
        container: "mpegts",
        codec: "h264",
        width: 160,
        height: 90,
        fps: 30.0,
        seconds: 8.0,
    };
    check_clip(&p, &e, 4);
}
