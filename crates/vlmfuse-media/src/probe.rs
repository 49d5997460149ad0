//! Opening a clip, classifying what is wrong with it, and reading its header.

use std::ffi::CString;
use std::fs::File;
use std::io::Read;
use std::path::Path;
use std::sync::OnceLock;

use ff::ffi;
use ff::format::context::Input;
use ff::media;
use ffmpeg_next as ff;

use crate::{ClipInfo, MediaError, MediaLimits};

/// Initialises FFmpeg once per process. Its log is lowered to errors because the warnings it
/// prints for ordinary user files (odd timestamps, deprecated pixel formats) would flood the
/// server's stderr; the failures that matter come back as [`MediaError`]s.
pub(crate) fn init() -> Result<(), MediaError> {
    static INIT: OnceLock<bool> = OnceLock::new();
    let ok = *INIT.get_or_init(|| {
        let ok = ff::init().is_ok();
        ff::log::set_level(ff::log::Level::Error);
        ok
    });
    if ok {
        Ok(())
    } else {
        Err(MediaError::Internal("FFmpeg failed to initialise".into()))
    }
}

/// An opened clip, validated against the limits, ready to decode.
pub(crate) struct Opened {
    pub ictx: Input,
    pub stream_index: usize,
    pub info: ClipInfo,
    /// Stream time base, seconds per tick.
    pub time_base: f64,
    /// Stream start, in ticks; subtracted so times count from the first frame.
    pub start_pts: i64,
    /// Keyframe times from the container index, seconds from the stream start, sorted.
    pub keyframes: Vec<f64>,
}

/// Above this probe score a format detection is trustworthy (FFmpeg's own "retry with more
/// data" threshold, `AVPROBE_SCORE_MAX / 4`).
const CONFIDENT_PROBE_SCORE: i32 = 25;

pub(crate) fn open(path: &Path, limits: &MediaLimits) -> Result<Opened, MediaError> {
    let meta = std::fs::metadata(path)?;
    if !meta.is_file() {
        return Err(MediaError::Io(std::io::Error::new(
            std::io::ErrorKind::InvalidInput,
            format!("{} is not a regular file", path.display()),
        )));
    }
    let bytes = meta.len();
    if bytes == 0 {
        return Err(MediaError::Empty);
    }
    if bytes > limits.max_bytes {
        return Err(MediaError::TooLarge {
            bytes,
            max_bytes: limits.max_bytes,
        });
    }
    init()?;

    let ictx = match ff::format::input(path) {
        Ok(ictx) => ictx,
        Err(e) => return Err(classify_open_error(path, e)),
    };

    // FFmpeg opens almost anything with *some* demuxer: a low score is a guess from noise
    // (random bytes "look like" ANSI art or MPEG-PS), and image demuxers turn a photo into a
    // one-frame "video". Neither is a clip.
    let format = ictx.format().name().to_string();
    if ictx.probe_score() <= CONFIDENT_PROBE_SCORE
        || format == "tty"
        || format == "image2"
        || format.ends_with("_pipe")
    {
        return Err(MediaError::NotVideo);
    }

    let Some(stream_index) = pick_video_stream(&ictx) else {
        return Err(MediaError::NoVideoStream);
    };

    let st = ictx
        .stream(stream_index)
        .ok_or_else(|| MediaError::Internal("video stream vanished".into()))?;
    let params = st.parameters();
    let codec_id = params.id();
    // SAFETY: `params` wraps the stream's live AVCodecParameters.
    let (width, height) = unsafe {
        let p = params.as_ptr();
        ((*p).width, (*p).height)
    };
    let codec = codec_id.name().to_string();
    if codec_id == ff::codec::Id::None {
        return Err(MediaError::UnsupportedCodec("unknown".into()));
    }
    // SAFETY: plain lookup in FFmpeg's static codec table.
    if unsafe { ffi::avcodec_find_decoder(codec_id.into()) }.is_null() {
        return Err(MediaError::UnsupportedCodec(codec));
    }
    if width <= 0 || height <= 0 {
        return Err(MediaError::Corrupt(format!(
            "video stream has no picture size ({width}x{height})"
        )));
    }
    let (width, height) = (width as u32, height as u32);
    let (long, short) = (width.max(height), width.min(height));
    let (max_long, max_short) = (
        limits.max_width.max(limits.max_height),
        limits.max_width.min(limits.max_height),
    );
    if long > max_long || short > max_short {
        return Err(MediaError::ResolutionTooHigh {
            width,
            height,
            max_width: limits.max_width,
            max_height: limits.max_height,
        });
    }

    let time_base = rational(st.time_base()).unwrap_or(0.0);
    if time_base <= 0.0 {
        return Err(MediaError::Corrupt("video stream has no time base".into()));
    }
    let start_pts = match st.start_time() {
        ffi::AV_NOPTS_VALUE => 0,
        t => t,
    };
    let fps = rational(st.avg_frame_rate())
        .or_else(|| rational(st.rate()))
        .filter(|f| *f > 0.0 && *f < 1000.0);

    let stream_duration = positive(st.duration()).map(|d| d as f64 * time_base);
    let container_duration = positive(ictx.duration()).map(|d| d as f64 / 1e6);
    let frames_duration = match (positive(st.frames()), fps) {
        (Some(n), Some(f)) => Some(n as f64 / f),
        _ => None,
    };
    let duration_s = [stream_duration, container_duration, frames_duration]
        .into_iter()
        .flatten()
        .find(|d| d.is_finite() && *d > 0.0)
        .ok_or_else(|| MediaError::Corrupt("the clip's duration is unknown".into()))?;
    if duration_s > limits.max_duration_s {
        return Err(MediaError::TooLong {
            duration_s,
            max_duration_s: limits.max_duration_s,
        });
    }
    let fps = fps
        .or_else(|| frames_duration.and(positive(st.frames()).map(|n| n as f64 / duration_s)))
        .unwrap_or(0.0);

    let keyframes = index_keyframes(&ictx, stream_index, time_base, start_pts);
    let keyframe_interval_s = if intra_only(codec_id) && fps > 0.0 {
        Some(1.0 / fps)
    } else {
        match keyframes.len() {
            0 => None,
            1 => Some(duration_s),
            n => Some((keyframes[n - 1] - keyframes[0]) / (n - 1) as f64),
        }
    };

    let container = container_name(&ictx, &codec);
    let info = ClipInfo {
        container,
        codec,
        duration_s,
        width,
        height,
        fps,
        keyframe_interval_s,
    };
    tracing::debug!(?info, path = %path.display(), "probed clip");
    Ok(Opened {
        ictx,
        stream_index,
        info,
        time_base,
        start_pts,
        keyframes,
    })
}

/// When FFmpeg cannot open a file, tells "not media at all" from "media, but broken" by
/// probing its first bytes ourselves: a confident format detection means a known container
/// whose structure is damaged (typically a truncated MP4 that lost its `moov` box).
fn classify_open_error(path: &Path, err: ff::Error) -> MediaError {
    use ff::error::{EACCES, EIO, EISDIR, ENOENT, ENOMEM, EPERM};
    match err {
        ff::Error::Other { errno: ENOMEM } => {
            MediaError::Internal(format!("opening the clip: {err}"))
        }
        ff::Error::Other {
            errno: errno @ (EACCES | EIO | EISDIR | ENOENT | EPERM),
        } => MediaError::Io(std::io::Error::from_raw_os_error(errno)),
        _ => match probe_head(path) {
            Some(format) => MediaError::Corrupt(format!("{format} container: {err}")),
            None => MediaError::NotVideo,
        },
    }
}

/// Runs FFmpeg's format detection on the first 64 KiB and returns the demuxer name when it
/// is confident.
fn probe_head(path: &Path) -> Option<String> {
    const HEAD: usize = 64 * 1024;
    let mut buf = Vec::with_capacity(HEAD + ffi::AVPROBE_PADDING_SIZE as usize);
    File::open(path)
        .ok()?
        .take(HEAD as u64)
        .read_to_end(&mut buf)
        .ok()?;
    let size = buf.len();
    if size == 0 {
        return None;
    }
    buf.resize(size + ffi::AVPROBE_PADDING_SIZE as usize, 0);
    // An empty name: the extension of a server-side temp file says nothing about the content.
    let name = CString::default();
    let pd = ffi::AVProbeData {
        filename: name.as_ptr(),
        buf: buf.as_mut_ptr(),
        buf_size: size as i32,
        mime_type: std::ptr::null(),
    };
    let mut score = CONFIDENT_PROBE_SCORE;
    // SAFETY: `pd` points at a zero-padded buffer that outlives the call.
    let fmt = unsafe { ffi::av_probe_input_format2(&pd, 1, &mut score) };
    if fmt.is_null() {
        return None;
    }
    // SAFETY: a non-null result is a static AVInputFormat with a static name.
    let name = unsafe { std::ffi::CStr::from_ptr((*fmt).name) };
    Some(name.to_string_lossy().into_owned())
}

/// The largest real video stream; cover art (attached pictures) does not count as video.
fn pick_video_stream(ictx: &Input) -> Option<usize> {
    ictx.streams()
        .filter(|st| st.parameters().medium() == media::Type::Video)
        .filter(|st| {
            !st.disposition()
                .contains(ff::format::stream::Disposition::ATTACHED_PIC)
        })
        .map(|st| {
            // SAFETY: reading plain fields of the stream's live AVCodecParameters.
            let area = unsafe {
                let p = st.parameters().as_ptr();
                i64::from((*p).width.max(0)) * i64::from((*p).height.max(0))
            };
            (st.index(), area)
        })
        // Largest area wins; on a tie the earlier stream (max_by_key keeps the last maximum,
        // so compare on the negated index too).
        .max_by_key(|&(index, area)| (area, std::cmp::Reverse(index)))
        .map(|(index, _)| index)
}

/// Keyframe times the demuxer already knows (MP4 `stss`, Matroska cues, AVI `idx1`), in
/// seconds from the stream start. Reading them costs nothing more, and they tell exactly
/// whether a seek would skip any decoding.
fn index_keyframes(ictx: &Input, stream_index: usize, time_base: f64, start: i64) -> Vec<f64> {
    let Some(st) = ictx.stream(stream_index) else {
        return Vec::new();
    };
    // SAFETY: the stream pointer is live for as long as `ictx`; the index accessors only read.
    let mut times: Vec<f64> = unsafe {
        let ptr = st.as_ptr() as *mut ffi::AVStream;
        let n = ffi::avformat_index_get_entries_count(ptr);
        (0..n)
            .filter_map(|i| {
                let e = ffi::avformat_index_get_entry(ptr, i);
                if e.is_null() || (*e).flags() & ffi::AVINDEX_KEYFRAME == 0 {
                    return None;
                }
                Some(((*e).timestamp.saturating_sub(start)) as f64 * time_base)
            })
            .filter(|t| t.is_finite())
            .collect()
    };
    times.sort_by(f64::total_cmp);
    times.dedup();
    times
}

/// Codecs where every frame is a keyframe (MJPEG, ProRes...): seeking is always cheap.
pub(crate) fn intra_only(id: ff::codec::Id) -> bool {
    // SAFETY: plain lookup in FFmpeg's static descriptor table.
    unsafe {
        let d = ffi::avcodec_descriptor_get(id.into());
        !d.is_null() && (*d).props & ffi::AV_CODEC_PROP_INTRA_ONLY != 0
    }
}

/// FFmpeg names some demuxers after every container they read ("mov,mp4,m4a,3gp,3g2,mj2",
/// "matroska,webm"); users want the one their file is.
fn container_name(ictx: &Input, codec: &str) -> String {
    let name = ictx.format().name().to_string();
    if name.starts_with("mov,") {
        let brand = ictx
            .metadata()
            .get("major_brand")
            .map(str::trim)
            .map(str::to_owned);
        return match brand.as_deref() {
            Some("qt") => "mov".into(),
            Some(b) if b.starts_with("3g") => "3gp".into(),
            _ => "mp4".into(),
        };
    }
    if name.starts_with("matroska") {
        // WebM is Matroska restricted to VP8/VP9/AV1 video.
        return if matches!(codec, "vp8" | "vp9" | "av1") {
            "webm".into()
        } else {
            "matroska".into()
        };
    }
    name.split(',').next().unwrap_or_default().to_string()
}

fn rational(r: ff::Rational) -> Option<f64> {
    (r.numerator() > 0 && r.denominator() > 0)
        .then(|| f64::from(r.numerator()) / f64::from(r.denominator()))
}

fn positive(v: i64) -> Option<i64> {
    (v > 0 && v != ffi::AV_NOPTS_VALUE).then_some(v)
}
