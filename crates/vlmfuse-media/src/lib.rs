//! Clip decoding and frame sampling for vlmfuse.
//!
//! The vision-language models that vlmfuse fuses see a clip as a handful of still frames, so
//! this crate turns an uploaded dashcam clip into `N` RGB frames spread over its length, as
//! cheaply as possible and without trusting the upload:
//!
//! * [`probe`] reads the header only, so the server can reject oversized, overlong or
//!   non-video uploads before spending any decoding time on them. Only the containers users
//!   send open (mp4/mov, matroska/webm, avi, mpeg-ts), chosen from the bytes and never from the
//!   upload's name, and nothing but the upload itself is ever read: playlists that name other
//!   files (HLS, ffconcat) are refused before FFmpeg sees them.
//! * [`sample_frames`] decodes only what it needs: it seeks to the keyframe before a target
//!   when that skips work and decodes forward when the next target is close, choosing per
//!   clip from the keyframe index (seeking loses on short clips with sparse keyframes).
//!
//! * MP4/MOV sample tables are checked before FFmpeg reads them (`mp4scan`): FFmpeg allocates
//!   for every sample a table declares, so a few KB declaring millions of samples would cost
//!   gigabytes; such files are refused with [`MediaError::TooManySamples`].
//! * The limits hold for every decoded frame, not only for the header (a stream can change
//!   resolution midway), and the decode work itself is bounded
//!   ([`MediaLimits::max_frames_decoded`]), not only the file size.
//!
//! Both functions block (FFmpeg is synchronous); async callers run them in
//! `tokio::task::spawn_blocking` and pass an [`Interrupt`] (the `_with_interrupt` variants) so
//! that a request that times out or goes away stops its decode. Every failure is a
//! [`MediaError`]; nothing panics on any input.

mod convert;
mod error;
mod interrupt;
mod mp4scan;
mod probe;
mod sample;

use std::path::Path;

use serde::{Deserialize, Serialize};

pub use error::{MediaError, MediaErrorClass};
pub use interrupt::{CancelOnDrop, Interrupt};
pub use sample::{DecodePolicy, DecodeStats};

/// The most frames one request may ask for: each 1080p RGB frame is 6 MB, so an unbounded
/// count would let one request exhaust memory.
pub const MAX_SAMPLE_FRAMES: usize = 512;

/// The largest side of any returned frame, for the same reason: [`FrameSize`] may not ask for
/// more, and a [`FrameSize::ShortSide`] resize of an extreme aspect ratio (an 8192x16 clip
/// scaled to a short side of 224 would be 114688 pixels long) is capped here on its long side.
pub const MAX_OUTPUT_SIDE: u32 = 8192;

/// What the server accepts, checked before any decoding so that a hostile or mistaken upload
/// costs almost nothing to refuse.
///
/// Resolution limits are orientation-agnostic: a portrait 2160x3840 clip passes the default
/// 3840x2160 limit, because phones record dashcam-style footage both ways and the cost is
/// the same.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct MediaLimits {
    /// Checked on the file size, before FFmpeg opens it.
    pub max_bytes: u64,
    /// Checked on the header's duration.
    pub max_duration_s: f64,
    /// Longest side allowed (with `max_height`, compared orientation-agnostically).
    pub max_width: u32,
    /// Shortest side allowed (with `max_width`, compared orientation-agnostically).
    pub max_height: u32,
    /// The most video frames one sampling may hand to the decoder. Bounds the decode work,
    /// which the file size does not: a 1 MB clip at 999 fps with one keyframe needs ~100k
    /// decodes to reach its end. Predicted from the keyframe index before decoding where the
    /// container has a complete one (MP4, AVI), and enforced while decoding for all.
    pub max_frames_decoded: u64,
    /// Threads FFmpeg's decoder may use for one clip (frame threading); 0: one per core, at
    /// most 8. Default 1: sampling is short decode runs between seeks, where frame threads add
    /// latency, and a server decodes several clips at once (see `DEFAULT_DECODE_THREADS`).
    pub decode_threads: usize,
}

/// See [`MediaLimits::decode_threads`]. One: sampling seeks before most targets and decodes
/// about half a GOP after each seek, and every seek drains FFmpeg's frame-thread pipeline, so
/// a second frame thread buys no latency on short runs (measured on the 20 s 720p clip, 8
/// frames: ~20-40% slower with 2 threads on 2 cores) and costs CPU that concurrent requests
/// need.
const DEFAULT_DECODE_THREADS: usize = 1;

impl Default for MediaLimits {
    /// 256 MiB, 2 minutes and 4K UHD: well above a typical dashcam clip (20–60 s of 1080p is
    /// 30–120 MB), well below what would tie up a decoding thread for long. 10,000 decoded
    /// frames admit the worst clip those limits let through (2 minutes at 60 fps with a single
    /// keyframe, ~6,750 decodes for 8 frames) and refuse the 100k-decode ones.
    fn default() -> Self {
        MediaLimits {
            max_bytes: 256 * 1024 * 1024,
            max_duration_s: 120.0,
            max_width: 3840,
            max_height: 2160,
            max_frames_decoded: 10_000,
            decode_threads: DEFAULT_DECODE_THREADS,
        }
    }
}

/// The size of the returned frames. Models have fixed input sizes, and scaling inside the
/// decoder's swscale pass is cheaper than a second resize of full-size RGB later.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum FrameSize {
    /// The clip's own pixel size (sample aspect ratio is ignored: dashcams use square pixels).
    #[default]
    Native,
    /// Keep the aspect ratio and make the shorter side this many pixels (upscaling if needed),
    /// the usual preprocessing of CLIP-style encoders before a centre crop.
    ShortSide(u32),
    /// Exactly this size, stretching if the aspect ratio differs.
    Exact { width: u32, height: u32 },
}

/// How many frames to sample and at what size.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(default)]
pub struct SampleOptions {
    /// Number of frames, spread uniformly over the clip (see [`target_times`]).
    pub frames: usize,
    /// Output size of every frame.
    pub size: FrameSize,
}

impl Default for SampleOptions {
    /// 8 frames cover a 20 s dashcam clip every 2.5 s while keeping model time and memory per
    /// request small.
    fn default() -> Self {
        SampleOptions {
            frames: 8,
            size: FrameSize::Native,
        }
    }
}

/// What the header says about a clip; returned by [`probe`] so the server can report and
/// validate a clip without decoding it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ClipInfo {
    /// Container short name: `mp4`, `mov`, `matroska`, `webm`, `avi`, ... (FFmpeg's demuxer
    /// name, narrowed for the demuxers that serve several containers).
    pub container: String,
    /// FFmpeg's codec name of the video stream (`h264`, `hevc`, `vp9`, `mpeg4`, `mjpeg`...).
    pub codec: String,
    /// Seconds, of the video stream when the container says, else of the whole file.
    pub duration_s: f64,
    /// Coded picture size in pixels.
    pub width: u32,
    /// Coded picture size in pixels.
    pub height: u32,
    /// Average frame rate; 0 when the container gives none.
    pub fps: f64,
    /// Mean spacing of keyframes in the container's index, in seconds. `None` when the
    /// container has no index (then sampling learns the spacing while decoding). It drives the
    /// seek-or-decode-forward choice, and is worth reporting because it predicts sampling cost.
    pub keyframe_interval_s: Option<f64>,
}

/// The shared frame type: packed RGB24 pixels and the presentation time (`pts_s`) of the
/// picture actually returned.
pub use vlmfuse_core::Frame;

/// One sampled frame: the [`Frame`] plus where it sits in the sample. Derefs to the frame, so
/// `f.rgb`, `f.width` and `f.pts_s` read as before; [`SampledFrame::frame`] is what models take.
#[derive(Debug, Clone, PartialEq)]
pub struct SampledFrame {
    /// Position in the sample, 0-based.
    pub index: usize,
    /// The time this frame was sampled for, seconds from the start of the video stream; the
    /// frame's `pts_s` is the first frame at or after it (or the last frame of the clip).
    pub target_s: f64,
    pub frame: Frame,
}

impl std::ops::Deref for SampledFrame {
    type Target = Frame;
    fn deref(&self) -> &Frame {
        &self.frame
    }
}

/// A clip's header information together with its sampled frames.
#[derive(Debug, Clone, PartialEq)]
pub struct DecodedClip {
    pub info: ClipInfo,
    pub frames: Vec<SampledFrame>,
}

impl DecodedClip {
    /// The presentation times of the frames, which the fusion step reports alongside each
    /// model's answer so that events can be placed on the clip's timeline.
    pub fn timestamps(&self) -> Vec<f64> {
        self.frames.iter().map(|f| f.pts_s).collect()
    }
}

/// The sampling targets for a clip: `t_j = duration * (j + 0.5) / n` for `j = 0..n`.
///
/// Centring each target in its `1/n` slice of the clip (rather than starting at 0 and ending
/// at the last frame) covers the clip evenly, avoids the black/fade-in first frame and the
/// often-missing last frame (a container's duration often overshoots its last frame).
pub fn target_times(duration_s: f64, n: usize) -> Vec<f64> {
    if !(duration_s.is_finite() && duration_s > 0.0) {
        return vec![0.0; n];
    }
    (0..n)
        .map(|j| duration_s * (j as f64 + 0.5) / n as f64)
        .collect()
}

/// Reads a clip's header and checks it against `limits`, without decoding any frame.
///
/// Blocking; call it from `spawn_blocking` in async code.
pub fn probe(path: &Path, limits: &MediaLimits) -> Result<ClipInfo, MediaError> {
    probe_with_interrupt(path, limits, &Interrupt::new())
}

/// [`probe`] that stops with [`MediaError::Cancelled`] or [`MediaError::DeadlineExceeded`]
/// when `interrupt` says so (checked before opening and before every read FFmpeg makes).
pub fn probe_with_interrupt(
    path: &Path,
    limits: &MediaLimits,
    interrupt: &Interrupt,
) -> Result<ClipInfo, MediaError> {
    probe::open(path, limits, interrupt).map(|opened| opened.info)
}

/// Samples `opts.frames` frames uniformly over the clip (see [`target_times`]), as RGB24 at
/// `opts.size`, after checking the clip against `limits`.
///
/// Each frame is the first decoded frame at or after its target time (or the last frame when
/// the clip ends before a target). The result is deterministic: the same file and options
/// give the same bytes.
///
/// Blocking; call it from `spawn_blocking` in async code.
pub fn sample_frames(
    path: &Path,
    opts: &SampleOptions,
    limits: &MediaLimits,
) -> Result<DecodedClip, MediaError> {
    sample_frames_with_interrupt(path, opts, limits, &Interrupt::new())
}

/// [`sample_frames`] that stops with [`MediaError::Cancelled`] or
/// [`MediaError::DeadlineExceeded`] when `interrupt` says so: checked before every read and
/// before every packet sent to the decoder, so an abandoned request frees its thread within
/// about one frame's decode.
pub fn sample_frames_with_interrupt(
    path: &Path,
    opts: &SampleOptions,
    limits: &MediaLimits,
    interrupt: &Interrupt,
) -> Result<DecodedClip, MediaError> {
    sample_frames_instrumented(path, opts, limits, DecodePolicy::Auto, interrupt)
        .map(|(clip, _)| clip)
}

/// [`sample_frames`] with an explicit decoding strategy, plus counters of the work done.
///
/// Exists for benchmarks and tests: every policy returns the same frames, only the cost
/// differs, and [`DecodePolicy::Everything`] is the naive baseline.
pub fn sample_frames_with_policy(
    path: &Path,
    opts: &SampleOptions,
    limits: &MediaLimits,
    policy: DecodePolicy,
) -> Result<(DecodedClip, DecodeStats), MediaError> {
    sample_frames_instrumented(path, opts, limits, policy, &Interrupt::new())
}

/// Everything at once: an explicit strategy, the work counters, and an interrupt.
pub fn sample_frames_instrumented(
    path: &Path,
    opts: &SampleOptions,
    limits: &MediaLimits,
    policy: DecodePolicy,
    interrupt: &Interrupt,
) -> Result<(DecodedClip, DecodeStats), MediaError> {
    sample::validate_options(opts)?;
    let opened = probe::open(path, limits, interrupt)?;
    sample::run(opened, opts, limits, policy, interrupt)
}

/// Samples the first frame at or after each of `times` (seconds from the start of the video
/// stream; finite, ascending, at most [`MAX_SAMPLE_FRAMES`]), as RGB24 at `size`, after checking the
/// clip against `limits`: for a model whose processor picks its own frames (Qwen3-VL's samples
/// frame indices at the checkpoint's fps, as transformers does). Same bounds and errors as
/// [`sample_frames`].
///
/// Blocking; call it from `spawn_blocking` in async code.
pub fn sample_frames_at(
    path: &Path,
    times: &[f64],
    size: FrameSize,
    limits: &MediaLimits,
    interrupt: &Interrupt,
) -> Result<DecodedClip, MediaError> {
    if times.iter().any(|t| !t.is_finite()) || times.windows(2).any(|w| w[1] < w[0]) {
        return Err(MediaError::InvalidOptions(
            "frame times must be finite and ascending".into(),
        ));
    }
    sample::validate_options(&SampleOptions {
        frames: times.len().max(1),
        size,
    })?;
    let opened = probe::open(path, limits, interrupt)?;
    sample::run_at(opened, times, size, limits, DecodePolicy::Auto, interrupt).map(|(c, _)| c)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frame_times_must_be_finite_ascending_and_few_enough() {
        let p = Path::new("/nonexistent/clip.mp4");
        let l = MediaLimits::default();
        let i = Interrupt::new();
        for bad in [
            vec![1.0, 0.5],
            vec![f64::NAN],
            vec![0.0; MAX_SAMPLE_FRAMES + 1],
        ] {
            let e = sample_frames_at(p, &bad, FrameSize::Native, &l, &i).unwrap_err();
            assert!(matches!(e, MediaError::InvalidOptions(_)), "{e:?}");
        }
        // Good times reach the file (which is missing here).
        let e = sample_frames_at(p, &[0.0, 1.0], FrameSize::Native, &l, &i).unwrap_err();
        assert!(!matches!(e, MediaError::InvalidOptions(_)), "{e:?}");
    }

    #[test]
    fn targets_are_centred_in_equal_slices() {
        assert_eq!(target_times(8.0, 4), vec![1.0, 3.0, 5.0, 7.0]);
        assert_eq!(target_times(20.0, 1), vec![10.0]);
        assert!(target_times(20.0, 0).is_empty());
        for bad in [0.0, -1.0, f64::NAN, f64::INFINITY] {
            assert_eq!(target_times(bad, 2), vec![0.0, 0.0]);
        }
    }

    #[test]
    fn output_sizes() {
        use convert::output_size;
        assert_eq!(output_size(FrameSize::Native, 1280, 720), (1280, 720));
        assert_eq!(
            output_size(FrameSize::ShortSide(224), 1280, 720),
            (398, 224)
        );
        assert_eq!(
            output_size(FrameSize::ShortSide(224), 720, 1280),
            (224, 398)
        );
        assert_eq!(output_size(FrameSize::ShortSide(100), 100, 100), (100, 100));
        // The long side of an extreme aspect ratio is capped (it would be 10,000 and 114,688).
        assert_eq!(
            output_size(FrameSize::ShortSide(1), 10_000, 1),
            (MAX_OUTPUT_SIDE, 1)
        );
        assert_eq!(
            output_size(FrameSize::ShortSide(224), 8192, 16),
            (MAX_OUTPUT_SIDE, 224)
        );
        assert_eq!(
            output_size(FrameSize::ShortSide(MAX_OUTPUT_SIDE), 16, 8192),
            (MAX_OUTPUT_SIDE, MAX_OUTPUT_SIDE)
        );
        let exact = FrameSize::Exact {
            width: 336,
            height: 336,
        };
        assert_eq!(output_size(exact, 1280, 720), (336, 336));
    }

    #[test]
    fn error_classes() {
        let client = [
            MediaError::Empty,
            MediaError::NotVideo,
            MediaError::UnsupportedContainer("hls".into()),
            MediaError::TooManyFrames {
                frames: 2,
                max_frames: 1,
            },
            MediaError::TooManySamples {
                table: "stsz",
                declared: 2,
                limit: 1,
            },
            MediaError::NoVideoStream,
            MediaError::UnsupportedCodec("x".into()),
            MediaError::Corrupt("x".into()),
            MediaError::TooLarge {
                bytes: 2,
                max_bytes: 1,
            },
            MediaError::TooLong {
                duration_s: 2.0,
                max_duration_s: 1.0,
            },
            MediaError::ResolutionTooHigh {
                width: 2,
                height: 2,
                max_width: 1,
                max_height: 1,
            },
            MediaError::InvalidOptions("x".into()),
        ];
        let server = [
            MediaError::Io(std::io::Error::other("disk")),
            MediaError::Internal("x".into()),
        ];
        let interrupted = [MediaError::Cancelled, MediaError::DeadlineExceeded];
        let mut kinds = std::collections::HashSet::new();
        for e in &client {
            assert!(e.is_client_error(), "{e:?}");
            assert_ne!(e.class(), MediaErrorClass::Internal, "{e:?}");
            assert!(!e.is_interrupted(), "{e:?}");
            assert!(kinds.insert(e.kind()), "duplicate kind {}", e.kind());
        }
        for e in server.iter().chain(&interrupted) {
            assert!(!e.is_client_error(), "{e:?}");
            assert!(kinds.insert(e.kind()), "duplicate kind {}", e.kind());
        }
        assert!(interrupted.iter().all(MediaError::is_interrupted));
        assert!(!server.iter().any(MediaError::is_interrupted));
    }

    #[test]
    fn defaults() {
        let l = MediaLimits::default();
        assert_eq!(l.max_bytes, 256 << 20);
        assert_eq!(l.max_duration_s, 120.0);
        assert_eq!((l.max_width, l.max_height), (3840, 2160));
        assert_eq!(l.max_frames_decoded, 10_000);
        assert_eq!(l.decode_threads, DEFAULT_DECODE_THREADS);
        let o = SampleOptions::default();
        assert_eq!((o.frames, o.size), (8, FrameSize::Native));
    }
}
