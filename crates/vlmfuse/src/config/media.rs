//! `[media]`: what an upload to /v1/infer may be and how it is sampled.

use serde::{Deserialize, Serialize};
use std::path::PathBuf;

#[derive(clap::Args, Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct MediaConfig {
    /// Frames sampled uniformly per clip.
    #[arg(
        long = "media-frames",
        id = "media-frames",
        env = "VLMFUSE_MEDIA_FRAMES",
        required = false
    )]
    pub frames: usize,
    /// Frames are scaled so their shorter side is this many pixels (0, the default: the clip's
    /// own size). In-process models get the frames as decoded and their own processors resize
    /// them as their references do (any scaling here would come first and break that parity);
    /// remote reporters scale their copy with `[[reporter]] frame_short_side`.
    #[arg(
        long = "media-frame-short-side",
        id = "media-frame-short-side",
        env = "VLMFUSE_MEDIA_FRAME_SHORT_SIDE",
        required = false
    )]
    pub frame_short_side: u32,
    /// Most `video` parts in one request.
    #[arg(
        long = "media-max-clips",
        id = "media-max-clips",
        env = "VLMFUSE_MEDIA_MAX_CLIPS",
        required = false
    )]
    pub max_clips: usize,
    /// Bytes per clip, enforced while streaming the upload (413 above).
    #[arg(
        long = "media-max-bytes",
        id = "media-max-bytes",
        env = "VLMFUSE_MEDIA_MAX_BYTES",
        required = false
    )]
    pub max_bytes: u64,
    /// Longest clip, seconds.
    #[arg(
        long = "media-max-duration-s",
        id = "media-max-duration-s",
        env = "VLMFUSE_MEDIA_MAX_DURATION_S",
        required = false
    )]
    pub max_duration_s: f64,
    /// Largest resolution (orientation-agnostic).
    #[arg(
        long = "media-max-width",
        id = "media-max-width",
        env = "VLMFUSE_MEDIA_MAX_WIDTH",
        required = false
    )]
    pub max_width: u32,
    #[arg(
        long = "media-max-height",
        id = "media-max-height",
        env = "VLMFUSE_MEDIA_MAX_HEIGHT",
        required = false
    )]
    pub max_height: u32,
    /// Most frames decoded for one clip (decode work, which the byte size does not bound: a
    /// 1 MB clip at 999 fps with one keyframe needs ~100k decodes); 422 above.
    #[arg(
        long = "media-max-frames-decoded",
        id = "media-max-frames-decoded",
        env = "VLMFUSE_MEDIA_MAX_FRAMES_DECODED",
        required = false
    )]
    pub max_frames_decoded: u64,
    /// FFmpeg decoder threads per clip; 0: one per core (at most 8). 1 is fastest for sampling
    /// (short runs between seeks) while several clips decode at once.
    #[arg(
        long = "media-decode-threads",
        id = "media-decode-threads",
        env = "VLMFUSE_MEDIA_DECODE_THREADS",
        required = false
    )]
    pub decode_threads: usize,
    /// Seconds one /v1/infer request may take (replaces limits.request_timeout_s there).
    #[arg(
        long = "media-request-timeout-s",
        id = "media-request-timeout-s",
        env = "VLMFUSE_MEDIA_REQUEST_TIMEOUT_S",
        required = false
    )]
    pub request_timeout_s: f64,
    /// Slowest upload /v1/infer waits for, in bytes per second averaged from the first byte
    /// (after `upload_grace_s`); a slower or stalled one is refused with 408 `upload_too_slow`,
    /// so trickling clients cannot hold the concurrency slots until the request timeout.
    /// 0 disables the check.
    #[arg(
        long = "media-min-upload-bytes-per-s",
        id = "media-min-upload-bytes-per-s",
        env = "VLMFUSE_MEDIA_MIN_UPLOAD_BYTES_PER_S",
        required = false
    )]
    pub min_upload_bytes_per_s: u64,
    /// Seconds of an upload before `min_upload_bytes_per_s` applies (connection start-up,
    /// a slow first packet).
    #[arg(
        long = "media-upload-grace-s",
        id = "media-upload-grace-s",
        env = "VLMFUSE_MEDIA_UPLOAD_GRACE_S",
        required = false
    )]
    pub upload_grace_s: f64,
    /// Where uploads are spooled; unset: `spool/` under the data directory. `vlmfuse-clip-*`
    /// files in it are removed at startup (a killed run leaves its uploads behind), except
    /// those whose name carries the pid of a process that runs (another instance's).
    #[arg(
        long = "media-temp-dir",
        id = "media-temp-dir",
        env = "VLMFUSE_MEDIA_TEMP_DIR",
        required = false
    )]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub temp_dir: Option<PathBuf>,
}

impl Default for MediaConfig {
    fn default() -> Self {
        let l = vlmfuse_media::MediaLimits::default();
        Self {
            frames: 8,
            frame_short_side: 0,
            max_clips: 4,
            max_bytes: l.max_bytes,
            max_duration_s: l.max_duration_s,
            max_width: l.max_width,
            max_height: l.max_height,
            max_frames_decoded: l.max_frames_decoded,
            decode_threads: l.decode_threads,
            request_timeout_s: 300.0,
            min_upload_bytes_per_s: 16 * 1024,
            upload_grace_s: 10.0,
            temp_dir: None,
        }
    }
}

impl MediaConfig {
    pub fn limits(&self) -> vlmfuse_media::MediaLimits {
        vlmfuse_media::MediaLimits {
            max_bytes: self.max_bytes,
            max_duration_s: self.max_duration_s,
            max_width: self.max_width,
            max_height: self.max_height,
            max_frames_decoded: self.max_frames_decoded,
            decode_threads: self.decode_threads,
        }
    }

    pub fn sample_options(&self) -> vlmfuse_media::SampleOptions {
        vlmfuse_media::SampleOptions {
            frames: self.frames,
            size: if self.frame_short_side == 0 {
                vlmfuse_media::FrameSize::Native
            } else {
                vlmfuse_media::FrameSize::ShortSide(self.frame_short_side)
            },
        }
    }
}

#[cfg(test)]
mod tests {
    /// By default frames are decoded at the clip's own size: in-process models' processors
    /// resize them as their references do.
    #[test]
    fn frames_are_decoded_at_their_own_size_by_default() {
        let o = super::MediaConfig::default().sample_options();
        assert!(matches!(o.size, vlmfuse_media::FrameSize::Native), "{o:?}");
        let shipped: toml::Value =
            toml::from_str(include_str!("../../../../config/default.toml")).unwrap();
        assert_eq!(shipped["media"]["frame_short_side"].as_integer(), Some(0));
    }
}
