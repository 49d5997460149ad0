//! Uploads made to trick the media layer: playlists that point at server files, containers
//! nobody sends, frames that grow in the middle of a stream, extreme aspect ratios, clips that
//! cost 100k decodes, and decodes the caller abandons. Every clip is made here, at test time.

mod common;

use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::mpsc;
use std::time::{Duration, Instant};

use common::{ffmpeg, h264, make_clip};
use vlmfuse_media::{
    probe, probe_with_interrupt, sample_frames, sample_frames_instrumented,
    sample_frames_with_interrupt, DecodePolicy, FrameSize, Interrupt, MediaError, MediaLimits,
    SampleOptions, MAX_OUTPUT_SIDE,
};

fn sample(path: &Path) -> Result<vlmfuse_media::DecodedClip, MediaError> {
    sample_frames(path, &SampleOptions::default(), &MediaLimits::default())
}

/// Both entry points refuse `path` with `kind`, and no frame comes back.
fn refused(path: &Path, kind: &str) -> MediaError {
    let p = probe(path, &MediaLimits::default());
    let s = sample(path);
    match (&p, &s) {
        (Err(p), Err(s)) => {
            assert_eq!(p.kind(), kind, "{}: probe: {p}", path.display());
            assert_eq!(s.kind(), kind, "{}: sample: {s}", path.display());
        }
        _ => panic!(
            "{} was opened: probe {:?}, sample {:?}",
            path.display(),
            p.map(|i| i.container),
            s.map(|c| c.frames.len())
        ),
    }
    s.unwrap_err()
}

/// A real clip on disk, the "secret" a playlist tries to make the server read.
fn secret_clip(dir: &Path) -> PathBuf {
    make_clip(dir, "secret.mp4", (320, 240, 25, 2.0), &h264(&[]))
}

fn write(path: &Path, text: &str) -> PathBuf {
    std::fs::write(path, text).unwrap();
    path.to_path_buf()
}

/// Runs `f` on a thread and fails the test if it does not return within `limit`: a decode
/// that opens a FIFO blocks in `open(2)` until a writer comes, so a hang means it was opened.
fn returns_within<T: Send + 'static>(
    limit: Duration,
    fifo: &Path,
    f: impl FnOnce() -> T + Send + 'static,
) -> T {
    let (tx, rx) = mpsc::channel();
    std::thread::spawn(move || {
        let _ = tx.send(f());
    });
    match rx.recv_timeout(limit) {
        Ok(v) => v,
        Err(_) => {
            // Release the blocked reader so the process can exit, then fail.
            let _ = std::fs::OpenOptions::new().write(true).open(fifo);
            panic!("the upload made the decoder open {}", fifo.display());
        }
    }
}

fn mkfifo(path: &Path) {
    let st = Command::new("mkfifo").arg(path).status().expect("mkfifo");
    assert!(st.success());
}

#[test]
fn hls_playlists_naming_server_files_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let secret = secret_clip(dir.path());
    let abs = secret.display().to_string();
    let bodies = [
        // As in the report: a bare media playlist.
        format!("#EXTM3U\n#EXTINF:2,\nfile:{abs}\n"),
        format!("#EXTM3U\n#EXTINF:2,\n{abs}\n"),
        // The tags FFmpeg's HLS probe looks for: without the allow-list this decodes the
        // secret clip whatever the upload's name.
        format!("#EXTM3U\n#EXT-X-TARGETDURATION:2\n#EXTINF:2,\nfile:{abs}\n#EXT-X-ENDLIST\n"),
        format!("#EXTM3U\n#EXT-X-TARGETDURATION:2\n#EXTINF:2,\n{abs}\n#EXT-X-ENDLIST\n"),
        "#EXTM3U\n#EXT-X-MEDIA-SEQUENCE:0\n#EXTINF:2,\nsecret.mp4\n#EXT-X-ENDLIST\n".to_string(),
    ];
    for (i, body) in bodies.iter().enumerate() {
        for name in ["list.m3u8", "upload.mp4", "upload.bin"] {
            let p = write(&dir.path().join(format!("{i}-{name}")), body);
            let e = refused(&p, "unsupported_container");
            assert!(e.is_client_error(), "{e:?}");
            assert!(e.to_string().contains("hls"), "{e}");
        }
    }
}

#[test]
fn playlists_never_open_the_files_they_name() {
    // The named file is a FIFO: opening it for reading blocks until a writer appears, so the
    // call returning at all proves the decoder never tried.
    let dir = tempfile::tempdir().unwrap();
    let fifo = dir.path().join("secret.mp4");
    mkfifo(&fifo);
    let abs = fifo.display().to_string();
    let cases = [
        (
            "a.m3u8",
            format!("#EXTM3U\n#EXT-X-TARGETDURATION:2\n#EXTINF:2,\nfile:{abs}\n#EXT-X-ENDLIST\n"),
        ),
        (
            "b.mp4",
            "#EXTM3U\n#EXT-X-TARGETDURATION:2\n#EXTINF:2,\nsecret.mp4\n#EXT-X-ENDLIST\n".into(),
        ),
        (
            "c.ffconcat",
            "ffconcat version 1.0\nfile 'secret.mp4'\n".into(),
        ),
        ("d.txt", "ffconcat version 1.0\nfile secret.mp4\n".into()),
    ];
    for (name, body) in cases {
        let p = write(&dir.path().join(name), &body);
        let q = p.clone();
        let r = returns_within(Duration::from_secs(20), &fifo, move || {
            sample(&q).map(|c| c.frames.len())
        });
        let e = r.expect_err("a playlist must not decode");
        assert_eq!(e.kind(), "unsupported_container", "{name}: {e}");
    }
}

#[test]
fn ffconcat_files_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let secret = secret_clip(dir.path());
    for (name, body) in [
        // Relative names resolve next to the upload: other users' spooled uploads.
        (
            "a.ffconcat",
            "ffconcat version 1.0\nfile 'secret.mp4'\n".to_string(),
        ),
        (
            "b.mp4",
            "ffconcat version 1.0\nfile secret.mp4\nduration 2\n".into(),
        ),
        // FFmpeg's own "unsafe file name" check refuses this one with EPERM (once a 500).
        (
            "c.txt",
            format!("ffconcat version 1.0\nfile '{}'\n", secret.display()),
        ),
    ] {
        let p = write(&dir.path().join(name), &body);
        let e = refused(&p, "unsupported_container");
        assert!(e.to_string().contains("concat"), "{e}");
    }
}

#[test]
fn containers_outside_the_allow_list_are_refused() {
    // Real, decodable videos in containers dashcams and phones do not write. Each one is a
    // demuxer the server would otherwise expose to uploads.
    let dir = tempfile::tempdir().unwrap();
    let flv = make_clip(dir.path(), "a.flv", (160, 120, 25, 1.0), &["-c:v", "flv1"]);
    let nut = make_clip(dir.path(), "a.nut", (160, 120, 25, 1.0), &["-c:v", "mpeg4"]);
    let gif = make_clip(dir.path(), "a.gif", (64, 48, 10, 1.0), &[]);
    let y4m = make_clip(
        dir.path(),
        "a.y4m",
        (64, 48, 10, 1.0),
        &["-pix_fmt", "yuv420p"],
    );
    for (p, fmt) in [
        (&flv, "flv"),
        (&nut, "nut"),
        (&gif, "gif"),
        (&y4m, "yuv4mpegpipe"),
    ] {
        let e = refused(p, "unsupported_container");
        assert!(e.to_string().contains(fmt), "{}: {e}", p.display());
        // The extension is not what decides: the same bytes under an allowed name.
        let renamed = dir.path().join(format!("{fmt}.mp4"));
        std::fs::copy(p, &renamed).unwrap();
        refused(&renamed, "unsupported_container");
    }
}

#[test]
fn allowed_containers_open_whatever_their_name() {
    let dir = tempfile::tempdir().unwrap();
    let ts = make_clip(
        dir.path(),
        "a.ts",
        (320, 240, 25, 2.0),
        &h264(&["-g", "25"]),
    );
    let mp4 = make_clip(dir.path(), "a.mp4", (320, 240, 25, 2.0), &h264(&[]));
    for (src, container) in [(&ts, "mpegts"), (&mp4, "mp4")] {
        for name in ["upload.m3u8", "upload.txt", "upload"] {
            let p = dir.path().join(format!("{container}-{name}"));
            std::fs::copy(src, &p).unwrap();
            let info = probe(&p, &MediaLimits::default()).unwrap();
            assert_eq!(info.container, container, "{name}");
            let clip = sample(&p).unwrap();
            assert_eq!(clip.frames.len(), 8);
            assert_eq!((clip.frames[0].width, clip.frames[0].height), (320, 240));
        }
    }
}

#[test]
fn a_resolution_change_mid_stream_cannot_pass_the_limits() {
    // Two MPEG-TS segments back to back, as an adaptive stream is cut: the header (and the
    // probe) see the first one.
    let dir = tempfile::tempdir().unwrap();
    let small = make_clip(
        dir.path(),
        "small.ts",
        (320, 240, 25, 2.0),
        &h264(&["-g", "25"]),
    );
    // Timestamps continue where the first segment ends, as in a real stream.
    let big = make_clip(
        dir.path(),
        "big.ts",
        (1280, 720, 25, 2.0),
        &h264(&["-g", "25", "-output_ts_offset", "2"]),
    );
    let joined = dir.path().join("joined.ts");
    let mut f = std::fs::File::create(&joined).unwrap();
    f.write_all(&std::fs::read(&small).unwrap()).unwrap();
    f.write_all(&std::fs::read(&big).unwrap()).unwrap();
    drop(f);

    let limits = MediaLimits {
        max_width: 640,
        max_height: 480,
        ..MediaLimits::default()
    };
    let info = probe(&joined, &limits).expect("the header is within the limits");
    assert_eq!((info.width, info.height), (320, 240));
    for policy in [
        DecodePolicy::Auto,
        DecodePolicy::Forward,
        DecodePolicy::Seek,
        DecodePolicy::Everything,
    ] {
        let r = sample_frames_instrumented(
            &joined,
            &SampleOptions::default(),
            &limits,
            policy,
            &Interrupt::new(),
        );
        match r {
            Err(e @ MediaError::ResolutionTooHigh { .. }) => {
                assert!(e.is_client_error());
                assert!(e.to_string().contains("1280x720"), "{e}");
            }
            Err(e) => panic!("{policy:?}: wrong error {e:?}"),
            Ok((clip, _)) => panic!(
                "{policy:?}: frames past the limit came back: {:?}",
                clip.frames
                    .iter()
                    .map(|f| (f.width, f.height))
                    .collect::<Vec<_>>()
            ),
        }
    }
    // Far past the limits the decoder is not even allowed to allocate the picture; the error
    // is the same.
    let tiny = MediaLimits {
        max_width: 400,
        max_height: 300,
        ..MediaLimits::default()
    };
    let e = sample_frames_instrumented(
        &joined,
        &SampleOptions::default(),
        &tiny,
        DecodePolicy::Forward,
        &Interrupt::new(),
    )
    .unwrap_err();
    assert!(
        matches!(
            e,
            MediaError::ResolutionTooHigh {
                width: 1280,
                height: 720,
                ..
            }
        ),
        "{e:?}"
    );
    // Within the limits, the same file samples (at both sizes).
    let clip = sample(&joined).unwrap();
    let sizes: Vec<_> = clip.frames.iter().map(|f| (f.width, f.height)).collect();
    assert!(
        sizes.contains(&(320, 240)) && sizes.contains(&(1280, 720)),
        "{sizes:?}"
    );
}

#[test]
fn a_clip_exactly_at_the_limits_decodes() {
    // 1080 lines are coded as 1088 (whole macroblocks): the per-picture check must use the
    // picture's size, not the coded one.
    let dir = tempfile::tempdir().unwrap();
    let p = make_clip(dir.path(), "hd.mp4", (1920, 1080, 25, 0.4), &h264(&[]));
    let limits = MediaLimits {
        max_width: 1920,
        max_height: 1080,
        ..MediaLimits::default()
    };
    let clip = sample_frames(&p, &SampleOptions::default(), &limits).unwrap();
    assert!(clip
        .frames
        .iter()
        .all(|f| (f.width, f.height) == (1920, 1080)));
}

#[test]
fn extreme_aspect_ratios_cannot_blow_up_the_resize() {
    // 8192x16: a short-side resize to 224 would make each frame 114688x224 (77 MB of RGB).
    let dir = tempfile::tempdir().unwrap();
    let p = make_clip(dir.path(), "wide.mp4", (8192, 16, 10, 1.0), &h264(&[]));
    let limits = MediaLimits {
        max_width: 8192,
        max_height: 8192,
        ..MediaLimits::default()
    };
    for size in [
        FrameSize::ShortSide(224),
        FrameSize::ShortSide(MAX_OUTPUT_SIDE),
    ] {
        let opts = SampleOptions { frames: 4, size };
        match sample_frames(&p, &opts, &limits) {
            Ok(clip) => {
                for f in &clip.frames {
                    assert!(
                        f.width <= MAX_OUTPUT_SIDE && f.height <= MAX_OUTPUT_SIDE,
                        "{size:?}: {f:?}"
                    );
                    assert_eq!(f.rgb.len(), (f.width * f.height * 3) as usize);
                }
                // The short side is still the one asked for, the long one is capped.
                if let FrameSize::ShortSide(n) = size {
                    assert_eq!(clip.frames[0].height, n.min(MAX_OUTPUT_SIDE));
                    assert_eq!(clip.frames[0].width, MAX_OUTPUT_SIDE);
                }
            }
            Err(e) => panic!("{size:?}: {e:?}"),
        }
    }
    // The same cap for a tall clip.
    let tall = make_clip(dir.path(), "tall.mp4", (16, 4096, 10, 1.0), &h264(&[]));
    let opts = SampleOptions {
        frames: 2,
        size: FrameSize::ShortSide(448),
    };
    let clip = sample_frames(&tall, &opts, &limits).unwrap();
    assert_eq!(
        (clip.frames[0].width, clip.frames[0].height),
        (448, MAX_OUTPUT_SIDE)
    );
}

/// 100 s at 999 fps with a single keyframe: about 100k decodes to reach the last target.
fn high_frame_rate_clip(dir: &Path, name: &str) -> PathBuf {
    let p = dir.join(name);
    ffmpeg(&[
        "-f",
        "lavfi",
        "-i",
        "color=c=red:size=16x16:rate=999:duration=100",
        "-c:v",
        "libx264",
        "-preset",
        "ultrafast",
        "-g",
        "200000",
        "-sc_threshold",
        "0",
        "-pix_fmt",
        "yuv420p",
        p.to_str().unwrap(),
    ]);
    p
}

#[test]
fn a_clip_that_needs_100k_decodes_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    // The MP4 index shows the one keyframe: refused before decoding anything.
    let mp4 = high_frame_rate_clip(dir.path(), "hfr.mp4");
    let limits = MediaLimits::default();
    let t = Instant::now();
    let e = sample_frames_instrumented(
        &mp4,
        &SampleOptions::default(),
        &limits,
        DecodePolicy::Auto,
        &Interrupt::new(),
    )
    .expect_err("100k decodes must be refused");
    let took = t.elapsed();
    assert!(
        matches!(e, MediaError::TooManyFrames { max_frames, .. } if max_frames == limits.max_frames_decoded),
        "{e:?}"
    );
    assert_eq!(e.kind(), "too_many_frames");
    assert!(e.is_client_error());
    assert!(took < Duration::from_secs(2), "refused after {took:?}");

    // MPEG-TS has no index: the budget stops the decoder as it goes.
    let ts = dir.path().join("hfr.ts");
    ffmpeg(&[
        "-i",
        mp4.to_str().unwrap(),
        "-c",
        "copy",
        ts.to_str().unwrap(),
    ]);
    let small = MediaLimits {
        max_frames_decoded: 2_000,
        ..MediaLimits::default()
    };
    for policy in [
        DecodePolicy::Auto,
        DecodePolicy::Forward,
        DecodePolicy::Everything,
    ] {
        let e = sample_frames_instrumented(
            &ts,
            &SampleOptions::default(),
            &small,
            policy,
            &Interrupt::new(),
        )
        .expect_err("stopped by the budget");
        assert!(
            matches!(
                e,
                MediaError::TooManyFrames {
                    max_frames: 2_000,
                    ..
                }
            ),
            "{policy:?}: {e:?}"
        );
    }
}

#[test]
fn good_clips_stay_within_the_default_budget() {
    // The paper's clips (20 s, 30 fps, one keyframe: forward decoding to the last target) and
    // a 2-minute 60 fps clip with one keyframe, the longest the default limits admit.
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("long.mp4");
    ffmpeg(&[
        "-f",
        "lavfi",
        "-i",
        "color=c=blue:size=64x36:rate=60:duration=120",
        "-c:v",
        "libx264",
        "-preset",
        "ultrafast",
        "-g",
        "100000",
        "-sc_threshold",
        "0",
        "-pix_fmt",
        "yuv420p",
        p.to_str().unwrap(),
    ]);
    let (clip, stats) = sample_frames_instrumented(
        &p,
        &SampleOptions::default(),
        &MediaLimits::default(),
        DecodePolicy::Auto,
        &Interrupt::new(),
    )
    .unwrap();
    assert_eq!(clip.frames.len(), 8);
    assert!(stats.packets > 6_000, "{stats:?}");
}

/// 30 s of 640x360 at 50 fps with one keyframe: 1,500 sequential decodes, about a second.
fn slow_clip(dir: &Path) -> PathBuf {
    make_clip(
        dir,
        "slow.mp4",
        (640, 360, 50, 30.0),
        &h264(&["-g", "100000", "-sc_threshold", "0"]),
    )
}

#[test]
fn a_deadline_stops_decoding() {
    let dir = tempfile::tempdir().unwrap();
    let p = slow_clip(dir.path());
    let opts = SampleOptions::default();
    let limits = MediaLimits::default();

    let t = Instant::now();
    sample_frames(&p, &opts, &limits).expect("the clip itself is fine");
    let full = t.elapsed();

    let deadline = Duration::from_millis(100);
    let t = Instant::now();
    let e = sample_frames_with_interrupt(&p, &opts, &limits, &Interrupt::with_timeout(deadline))
        .expect_err("the deadline must stop it");
    let took = t.elapsed();
    assert!(matches!(e, MediaError::DeadlineExceeded), "{e:?}");
    assert_eq!(e.kind(), "deadline_exceeded");
    assert!(!e.is_client_error());
    assert!(
        took < deadline + Duration::from_millis(400) && took * 3 < full,
        "stopped after {took:?} (the whole decode takes {full:?})"
    );

    // A deadline already past: nothing is opened (the interrupt callback refuses the open).
    let past = Interrupt::with_deadline(Instant::now() - Duration::from_millis(1));
    let e = probe_with_interrupt(&p, &limits, &past).unwrap_err();
    assert!(matches!(e, MediaError::DeadlineExceeded), "{e:?}");
    // A generous deadline changes nothing.
    let clip =
        sample_frames_with_interrupt(&p, &opts, &limits, &Interrupt::with_timeout(full * 20))
            .unwrap();
    assert_eq!(clip.frames.len(), 8);
}

#[test]
fn cancelling_stops_decoding() {
    let dir = tempfile::tempdir().unwrap();
    let p = slow_clip(dir.path());
    let opts = SampleOptions::default();
    let limits = MediaLimits::default();

    // Cancelled from another thread while it decodes, as when the request is abandoned.
    let interrupt = Interrupt::new();
    let remote = interrupt.clone();
    let canceller = std::thread::spawn(move || {
        std::thread::sleep(Duration::from_millis(100));
        remote.cancel();
        Instant::now()
    });
    let e = sample_frames_with_interrupt(&p, &opts, &limits, &interrupt).unwrap_err();
    let stopped = Instant::now();
    let cancelled_at = canceller.join().unwrap();
    assert!(matches!(e, MediaError::Cancelled), "{e:?}");
    assert_eq!(e.kind(), "cancelled");
    assert!(!e.is_client_error());
    assert!(
        stopped.duration_since(cancelled_at) < Duration::from_millis(300),
        "kept decoding for {:?} after the cancel",
        stopped.duration_since(cancelled_at)
    );

    // Already cancelled: refused at once.
    let e = sample_frames_with_interrupt(&p, &opts, &limits, &interrupt).unwrap_err();
    assert!(matches!(e, MediaError::Cancelled), "{e:?}");

    // The guard an async caller holds: dropping it (the request future went away) cancels.
    let interrupt = Interrupt::new();
    let guard = interrupt.cancel_on_drop();
    assert!(!interrupt.is_cancelled());
    drop(guard);
    assert!(interrupt.is_cancelled());
    let e = probe_with_interrupt(&p, &limits, &interrupt).unwrap_err();
    assert!(matches!(e, MediaError::Cancelled), "{e:?}");
    // Disarmed (the work finished): dropping no longer cancels.
    let interrupt = Interrupt::new();
    interrupt.cancel_on_drop().disarm();
    assert!(!interrupt.is_cancelled());
}
