//! Bad uploads: each one must come back as the right `MediaError`, never as a panic.

mod common;

use std::path::Path;

use common::{ffmpeg, h264, make_clip};
use vlmfuse_media::{
    probe, sample_frames, FrameSize, MediaError, MediaErrorClass, MediaLimits, SampleOptions,
    MAX_SAMPLE_FRAMES,
};

fn sample(path: &Path) -> Result<vlmfuse_media::DecodedClip, MediaError> {
    sample_frames(path, &SampleOptions::default(), &MediaLimits::default())
}

/// Both entry points give the same kind of error for a bad file.
fn both_fail(path: &Path) -> MediaError {
    let p = probe(path, &MediaLimits::default()).expect_err("probe should fail");
    let s = sample(path).expect_err("sampling should fail");
    assert_eq!(p.kind(), s.kind(), "{p} / {s}");
    s
}

/// Deterministic pseudo-random bytes (xorshift), so a failure reproduces.
fn noise(len: usize, mut seed: u64) -> Vec<u8> {
    (0..len)
        .map(|_| {
            seed ^= seed << 13;
            seed ^= seed >> 7;
            seed ^= seed << 17;
            (seed >> 24) as u8
        })
        .collect()
}

#[test]
fn empty_file() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("empty.mp4");
    std::fs::write(&p, b"").unwrap();
    let e = both_fail(&p);
    assert!(matches!(e, MediaError::Empty), "{e:?}");
    assert!(e.is_client_error());
    assert_eq!(e.kind(), "empty");
}

#[test]
fn random_bytes_are_not_video() {
    let dir = tempfile::tempdir().unwrap();
    for (i, len) in [1usize, 100, 4096, 300_000].into_iter().enumerate() {
        let p = dir.path().join(format!("noise{i}.mp4"));
        std::fs::write(&p, noise(len, 0x9E37_79B9_7F4A_7C15 + i as u64)).unwrap();
        let e = both_fail(&p);
        assert!(matches!(e, MediaError::NotVideo), "{len} bytes: {e:?}");
        assert_eq!(e.class(), MediaErrorClass::Unsupported);
        assert_eq!(e.kind(), "not_video");
    }
    let text = dir.path().join("notes.txt");
    std::fs::write(&text, "this is a plain text file, not a clip\n".repeat(50)).unwrap();
    let e = both_fail(&text);
    assert!(matches!(e, MediaError::NotVideo), "{e:?}");
}

#[test]
fn truncated_mp4_is_corrupt() {
    let dir = tempfile::tempdir().unwrap();
    for faststart in [false, true] {
        let mut args = h264(&["-g", "10"]);
        if faststart {
            // The index comes first, so the cut removes frame data instead of the index.
            args.extend_from_slice(&["-movflags", "+faststart"]);
        }
        let name = format!("full{faststart}.mp4");
        let p = make_clip(dir.path(), &name, (320, 240, 25, 4.0), &args);
        let bytes = std::fs::read(&p).unwrap();
        let cut = dir.path().join(format!("cut{faststart}.mp4"));
        std::fs::write(&cut, &bytes[..bytes.len() / 2]).unwrap();
        let e = sample(&cut).expect_err("half an mp4 must not sample");
        assert!(
            matches!(e, MediaError::Corrupt(_)),
            "faststart={faststart}: {e:?}"
        );
        assert!(e.is_client_error());
        if !faststart {
            // Without its index the header is unreadable, so probing fails already.
            let e = probe(&cut, &MediaLimits::default()).unwrap_err();
            assert!(matches!(e, MediaError::Corrupt(_)), "{e:?}");
        }
    }
}

#[test]
fn damaged_files_never_panic() {
    // Overwrite parts of valid clips with noise: any outcome but a panic is acceptable, and
    // errors must be client errors.
    let dir = tempfile::tempdir().unwrap();
    let sources = [
        make_clip(
            dir.path(),
            "a.mp4",
            (160, 120, 25, 2.0),
            &h264(&["-g", "10", "-movflags", "+faststart"]),
        ),
        make_clip(
            dir.path(),
            "a.mkv",
            (160, 120, 25, 2.0),
            &h264(&["-g", "10"]),
        ),
        make_clip(dir.path(), "a.avi", (160, 120, 25, 2.0), &["-c:v", "mpeg4"]),
    ];
    for (i, src) in sources.iter().enumerate() {
        let bytes = std::fs::read(src).unwrap();
        for (k, (from, to)) in [(0.3, 0.5), (0.05, 0.1), (0.6, 0.61), (0.0, 0.02)]
            .into_iter()
            .enumerate()
        {
            let mut b = bytes.clone();
            let (s, e) = (
                (b.len() as f64 * from) as usize,
                (b.len() as f64 * to) as usize,
            );
            let junk = noise(e - s, (i * 10 + k) as u64 + 1);
            b[s..e].copy_from_slice(&junk);
            let p = dir.path().join(format!("bad{i}{k}"));
            std::fs::write(&p, &b).unwrap();
            match sample(&p) {
                Ok(clip) => assert_eq!(clip.frames.len(), 8),
                Err(e) => assert!(e.is_client_error(), "{}: {e:?}", src.display()),
            }
        }
    }
}

#[test]
fn audio_only_files_have_no_video_stream() {
    let dir = tempfile::tempdir().unwrap();
    let m4a = dir.path().join("a.m4a");
    let mka = dir.path().join("a.mka");
    let wav = dir.path().join("a.wav");
    for (p, codec) in [(&m4a, "aac"), (&mka, "flac"), (&wav, "pcm_s16le")] {
        ffmpeg(&[
            "-f",
            "lavfi",
            "-i",
            "sine=frequency=440:duration=1",
            "-c:a",
            codec,
            p.to_str().unwrap(),
        ]);
        let e = both_fail(p);
        assert!(
            matches!(e, MediaError::NoVideoStream),
            "{}: {e:?}",
            p.display()
        );
        assert_eq!(e.kind(), "no_video_stream");
    }
}

#[test]
fn unknown_codec_is_unsupported() {
    // An AVI whose codec tag no decoder knows, as from an exotic camera.
    let dir = tempfile::tempdir().unwrap();
    let p = make_clip(dir.path(), "a.avi", (160, 120, 25, 1.0), &["-c:v", "mpeg4"]);
    let mut bytes = std::fs::read(&p).unwrap();
    let mut patched = 0;
    for i in 0..bytes.len().min(8192).saturating_sub(4) {
        if &bytes[i..i + 4] == b"FMP4" {
            bytes[i..i + 4].copy_from_slice(b"QQZX");
            patched += 1;
        }
    }
    assert!(patched > 0, "FourCC not found in the AVI header");
    std::fs::write(&p, &bytes).unwrap();
    let e = both_fail(&p);
    assert!(matches!(e, MediaError::UnsupportedCodec(_)), "{e:?}");
    assert_eq!(e.class(), MediaErrorClass::Unsupported);
    assert_eq!(e.kind(), "unsupported_codec");
}

#[test]
fn limits_are_enforced_before_decoding() {
    let dir = tempfile::tempdir().unwrap();
    let p = make_clip(dir.path(), "a.mp4", (320, 240, 25, 3.0), &h264(&[]));
    let size = std::fs::metadata(&p).unwrap().len();
    let opts = SampleOptions::default();

    let small = MediaLimits {
        max_bytes: size - 1,
        ..MediaLimits::default()
    };
    let e = sample_frames(&p, &opts, &small).unwrap_err();
    assert!(
        matches!(e, MediaError::TooLarge { bytes, max_bytes } if bytes == size && max_bytes == size - 1),
        "{e:?}"
    );
    assert_eq!(e.class(), MediaErrorClass::Oversized);
    assert_eq!(e.kind(), "too_large");
    let exact = MediaLimits {
        max_bytes: size,
        ..MediaLimits::default()
    };
    assert!(sample_frames(&p, &opts, &exact).is_ok());

    let short = MediaLimits {
        max_duration_s: 2.5,
        ..MediaLimits::default()
    };
    let e = probe(&p, &short).unwrap_err();
    assert!(
        matches!(e, MediaError::TooLong { duration_s, .. } if (duration_s - 3.0).abs() < 0.05),
        "{e:?}"
    );
    assert!(sample_frames(&p, &opts, &short).is_err());

    let low = MediaLimits {
        max_width: 320,
        max_height: 200,
        ..MediaLimits::default()
    };
    let e = sample_frames(&p, &opts, &low).unwrap_err();
    assert!(
        matches!(
            e,
            MediaError::ResolutionTooHigh {
                width: 320,
                height: 240,
                ..
            }
        ),
        "{e:?}"
    );
    // Orientation-agnostic: 240x320 limits accept a 320x240 clip.
    let portrait = MediaLimits {
        max_width: 240,
        max_height: 320,
        ..MediaLimits::default()
    };
    assert!(probe(&p, &portrait).is_ok());
}

#[test]
fn invalid_options_and_missing_files() {
    let dir = tempfile::tempdir().unwrap();
    let p = make_clip(dir.path(), "a.mp4", (160, 120, 25, 1.0), &h264(&[]));
    let limits = MediaLimits::default();
    for opts in [
        SampleOptions {
            frames: 0,
            size: FrameSize::Native,
        },
        SampleOptions {
            frames: MAX_SAMPLE_FRAMES + 1,
            size: FrameSize::Native,
        },
        SampleOptions {
            frames: 4,
            size: FrameSize::ShortSide(0),
        },
        SampleOptions {
            frames: 4,
            size: FrameSize::Exact {
                width: 10,
                height: 0,
            },
        },
    ] {
        let e = sample_frames(&p, &opts, &limits).unwrap_err();
        assert!(
            matches!(e, MediaError::InvalidOptions(_)),
            "{opts:?}: {e:?}"
        );
        assert!(e.is_client_error());
    }

    let e = sample(&dir.path().join("missing.mp4")).unwrap_err();
    assert!(matches!(e, MediaError::Io(_)), "{e:?}");
    assert!(!e.is_client_error());
    assert_eq!(e.class(), MediaErrorClass::Internal);
    assert_eq!(e.kind(), "io");
    let e = sample(dir.path()).unwrap_err();
    assert!(matches!(e, MediaError::Io(_)), "{e:?}");
}

#[test]
fn limits_and_options_deserialize_with_defaults() {
    let l: MediaLimits = serde_json::from_str(r#"{"max_duration_s": 30.0}"#).unwrap();
    assert_eq!(l.max_duration_s, 30.0);
    assert_eq!(l.max_bytes, 256 * 1024 * 1024);
    assert_eq!((l.max_width, l.max_height), (3840, 2160));
    let o: SampleOptions = serde_json::from_str(r#"{"size": {"short_side": 224}}"#).unwrap();
    assert_eq!(o.frames, 8);
    assert_eq!(o.size, FrameSize::ShortSide(224));
}
