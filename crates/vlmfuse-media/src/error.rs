//! The one error type of the crate.
//!
//! Uploads come from users, so most failures are the client's fault (a file that is not a
//! video, too long, broken). The variants are split finely enough that a front end can tell the
//! user *what* is wrong without parsing messages ([`MediaError::kind`]), and
//! [`MediaError::class`] groups them by what the caller can do about it. This crate speaks no
//! HTTP: the service maps classes to statuses in its one error-mapping place.
//! [`MediaError::is_interrupted`] marks the decodes that the caller's deadline or cancellation
//! stopped.

use thiserror::Error;

/// What the caller can do about a [`MediaError`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum MediaErrorClass {
    /// The upload is bigger than the limit on bytes.
    Oversized,
    /// Not a container, or a codec this build cannot decode: send another format.
    Unsupported,
    /// Nothing usable was sent: an empty file, or impossible sampling options.
    Malformed,
    /// A real video that breaks a limit or is broken (no picture track, corrupt, too long,
    /// too large a resolution).
    Rejected,
    /// The server's side (disk, FFmpeg internals): the upload may be fine.
    Internal,
    /// The caller's deadline passed or it cancelled: the upload may be fine; try again later.
    Interrupted,
}

/// Why a clip could not be probed or sampled.
#[derive(Debug, Error)]
pub enum MediaError {
    /// The file has zero bytes: usually an upload that never arrived, so it gets its own
    /// message instead of a confusing "not a video".
    #[error("the file is empty")]
    Empty,
    /// No demuxer recognises the bytes: the upload is not a media container at all.
    #[error("the file is not a video (no known container format)")]
    NotVideo,
    /// The bytes are a format FFmpeg knows but uploads may not use: only mp4/mov,
    /// matroska/webm, avi and mpegts open. Playlists (HLS, ffconcat) name other files, which
    /// would make the server read its own disk; the other demuxers are attack surface nobody's
    /// dashcam needs. Holds FFmpeg's name of what the bytes are.
    #[error("the {0} format is not accepted; send mp4, mov, mkv, webm, avi or mpeg-ts")]
    UnsupportedContainer(String),
    /// A real media file without a decodable picture track (audio-only, subtitles, a
    /// still cover image).
    #[error("the file has no video stream")]
    NoVideoStream,
    /// The container is fine but this FFmpeg build has no decoder for the video codec.
    #[error("unsupported video codec: {0}")]
    UnsupportedCodec(String),
    /// The container was recognised but its data is broken or truncated.
    #[error("the video is corrupt or truncated: {0}")]
    Corrupt(String),
    /// Rejected before opening, so a huge upload costs no decoding time.
    #[error("the file is {bytes} bytes, more than the limit of {max_bytes}")]
    TooLarge { bytes: u64, max_bytes: u64 },
    /// Rejected from the header, before decoding.
    #[error("the clip lasts {duration_s:.1} s, more than the limit of {max_duration_s:.1} s")]
    TooLong {
        duration_s: f64,
        max_duration_s: f64,
    },
    /// Rejected from the header before decoding, and checked again on every decoded frame
    /// (a stream may change resolution midway): decoding cost and memory grow with the pixel
    /// count.
    #[error("the clip is {width}x{height}, more than the limit of {max_width}x{max_height}")]
    ResolutionTooHigh {
        width: u32,
        height: u32,
        max_width: u32,
        max_height: u32,
    },
    /// Sampling would decode more frames than [`crate::MediaLimits::max_frames_decoded`]: a
    /// very high frame rate with few keyframes (999 fps and one keyframe is ~100k decodes).
    /// Either predicted from the container's keyframe index before decoding, or reached while
    /// decoding; `frames` is then a lower bound of what the clip would have needed.
    #[error(
        "sampling this clip needs at least {frames} decoded frames, more than the limit of \
         {max_frames} (a very high frame rate with few keyframes)"
    )]
    TooManyFrames { frames: u64, max_frames: u64 },
    /// An MP4/MOV whose sample tables declare more samples or entries than the file could
    /// hold or the limits allow (a 3 KB file claiming 80 million samples), refused by a scan
    /// of the box headers before FFmpeg, which would allocate for every declared entry, opens
    /// it. `table` is the box that declared them (`stsz`, `trun`, ...); `declared` is its count
    /// (for `stsz`/`trun`: the file's running total of samples) and `limit` what it may be:
    /// what the box has bytes for, or the limit derived from
    /// [`crate::MediaLimits::max_duration_s`].
    #[error(
        "the container's {table} table declares {declared} samples or entries, more than the \
         {limit} this file can hold or the limits allow"
    )]
    TooManySamples {
        table: &'static str,
        declared: u64,
        limit: u64,
    },
    /// The request asked for something impossible (zero frames, a zero-sized output, ...).
    #[error("invalid sampling options: {0}")]
    InvalidOptions(String),
    /// The file could not be read (missing, permissions, disk): a server-side problem,
    /// since the server wrote the file itself.
    #[error("i/o error: {0}")]
    Io(#[from] std::io::Error),
    /// FFmpeg failed in a way that says nothing about the input (allocation, scaler setup).
    #[error("internal media error: {0}")]
    Internal(String),
    /// The caller cancelled the [`crate::Interrupt`] (the request was abandoned); decoding
    /// stopped at the next packet or read.
    #[error("decoding was cancelled")]
    Cancelled,
    /// The [`crate::Interrupt`]'s deadline passed before the clip was sampled.
    #[error("decoding did not finish before its deadline")]
    DeadlineExceeded,
}

impl MediaError {
    /// Whether the request (the uploaded file or the options) is at fault rather than the
    /// server. Interrupted decodes are not: the upload may be fine, the caller stopped waiting.
    pub fn is_client_error(&self) -> bool {
        !matches!(
            self.class(),
            MediaErrorClass::Internal | MediaErrorClass::Interrupted
        )
    }

    /// Whether the caller's [`crate::Interrupt`] stopped the decode (cancelled or past its
    /// deadline), as opposed to anything about the clip.
    pub fn is_interrupted(&self) -> bool {
        self.class() == MediaErrorClass::Interrupted
    }

    pub fn class(&self) -> MediaErrorClass {
        match self {
            MediaError::TooLarge { .. } => MediaErrorClass::Oversized,
            MediaError::NotVideo
            | MediaError::UnsupportedContainer(_)
            | MediaError::UnsupportedCodec(_) => MediaErrorClass::Unsupported,
            MediaError::Empty | MediaError::InvalidOptions(_) => MediaErrorClass::Malformed,
            MediaError::NoVideoStream
            | MediaError::Corrupt(_)
            | MediaError::TooLong { .. }
            | MediaError::ResolutionTooHigh { .. }
            | MediaError::TooManyFrames { .. }
            | MediaError::TooManySamples { .. } => MediaErrorClass::Rejected,
            MediaError::Io(_) | MediaError::Internal(_) => MediaErrorClass::Internal,
            MediaError::Cancelled | MediaError::DeadlineExceeded => MediaErrorClass::Interrupted,
        }
    }

    /// A short, stable, machine-readable name for API responses and metric labels, so that
    /// clients and dashboards do not depend on the wording of messages.
    pub fn kind(&self) -> &'static str {
        match self {
            MediaError::Empty => "empty",
            MediaError::NotVideo => "not_video",
            MediaError::UnsupportedContainer(_) => "unsupported_container",
            MediaError::NoVideoStream => "no_video_stream",
            MediaError::UnsupportedCodec(_) => "unsupported_codec",
            MediaError::Corrupt(_) => "corrupt",
            MediaError::TooLarge { .. } => "too_large",
            MediaError::TooLong { .. } => "too_long",
            MediaError::ResolutionTooHigh { .. } => "resolution_too_high",
            MediaError::TooManyFrames { .. } => "too_many_frames",
            MediaError::TooManySamples { .. } => "too_many_samples",
            MediaError::InvalidOptions(_) => "invalid_options",
            MediaError::Io(_) => "io",
            MediaError::Internal(_) => "internal",
            MediaError::Cancelled => "cancelled",
            MediaError::DeadlineExceeded => "deadline_exceeded",
        }
    }
}
