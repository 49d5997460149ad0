//! Opening a clip, classifying what is wrong with it, and reading its header.

use std::ffi::{c_char, c_int, c_void, CStr, CString};
use std::fs::File;
use std::io::Read;
use std::os::unix::ffi::OsStrExt;
use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Mutex, OnceLock};

use ff::ffi;
use ff::format::context::Input;
use ff::media;
use ffmpeg_next as ff;

use crate::{ClipInfo, Interrupt, MediaError, MediaLimits};

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
    /// Owns what FFmpeg's callbacks point at; must outlive `ictx` (declared after it, so it
    /// is dropped after it, and moved along with it).
    pub guard: OpenGuard,
    pub stream_index: usize,
    pub info: ClipInfo,
    /// Stream time base, seconds per tick.
    pub time_base: f64,
    /// Stream start, in ticks; subtracted so times count from the first frame.
    pub start_pts: i64,
    /// Keyframe times from the container index, seconds from the stream start, sorted.
    pub keyframes: Vec<f64>,
    /// Whether the index lists every keyframe (MP4 `stss`, AVI `idx1`), so that the decode
    /// work of a sample can be predicted from it. Matroska cues may list only some.
    pub complete_index: bool,
}

/// Above this probe score a format detection is trustworthy (FFmpeg's own "retry with more
/// data" threshold, `AVPROBE_SCORE_MAX / 4`).
const CONFIDENT_PROBE_SCORE: i32 = 25;

/// The demuxers an upload may open, by FFmpeg's name: the containers phones and dashcams
/// write. Everything else FFmpeg can read (playlists that name other files, image sequences,
/// raw pipes, network-ish formats, ~300 rarely fuzzed demuxers) is refused before FFmpeg opens
/// anything, whatever the upload's name says.
pub(crate) const ALLOWED_DEMUXERS: [&str; 4] =
    ["mov,mp4,m4a,3gp,3g2,mj2", "matroska,webm", "avi", "mpegts"];

/// Audio containers: refused like the other disallowed formats, but with the message that
/// helps ("no video stream") rather than "format not accepted".
const AUDIO_DEMUXERS: [&str; 12] = [
    "wav", "mp3", "flac", "aac", "aiff", "ogg", "w64", "ac3", "eac3", "amr", "wv", "ape",
];

/// How much of the file format detection may read, as FFmpeg's own probing does.
const PROBE_MAX_BYTES: usize = 1 << 20;
const PROBE_MIN_BYTES: usize = 2048;

pub(crate) fn open(
    path: &Path,
    limits: &MediaLimits,
    interrupt: &Interrupt,
) -> Result<Opened, MediaError> {
    interrupt.check()?;
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

    let head = read_head(path)?;
    let format = detect_format(&head)?;
    // SAFETY: `format` came from FFmpeg's static demuxer table; its name is static.
    let demuxer = unsafe { CStr::from_ptr((*format).name) };
    if demuxer.to_bytes().starts_with(b"mov,") {
        // Before FFmpeg reads the sample tables, which it allocates for by declared count.
        crate::mp4scan::check(path, bytes, limits)?;
    }
    let (ictx, guard) = open_input(path, format, interrupt)?;

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
    // MP4 `stss` and AVI `idx1` list every keyframe; Matroska cues need not, and MPEG-TS has
    // no index at all.
    let demuxer = ictx.format().name().to_string();
    let complete_index = !keyframes.is_empty() && (demuxer.starts_with("mov,") || demuxer == "avi");
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
        guard,
        stream_index,
        info,
        time_base,
        start_pts,
        keyframes,
        complete_index,
    })
}

/// The first bytes of the file, zero-padded as FFmpeg's probe functions require.
fn read_head(path: &Path) -> Result<Vec<u8>, MediaError> {
    let mut buf = Vec::with_capacity(PROBE_MAX_BYTES + ffi::AVPROBE_PADDING_SIZE as usize);
    File::open(path)?
        .take(PROBE_MAX_BYTES as u64)
        .read_to_end(&mut buf)?;
    Ok(buf)
}

/// Decides the demuxer from the bytes alone, with an allow-list.
///
/// FFmpeg's own probing also weighs the file name (a `.m3u8` or `.ffconcat` suffix is enough to
/// pick those demuxers), and the name of a spooled upload is the client's to choose, so it is
/// never given. Probing grows the window from 2 KiB to 1 MiB as FFmpeg does, stopping at the
/// first confident answer; the answer must then be on [`ALLOWED_DEMUXERS`].
fn detect_format(head: &[u8]) -> Result<*const ffi::AVInputFormat, MediaError> {
    if let Some(kind) = sniff_playlist(head) {
        return Err(MediaError::UnsupportedContainer(kind.into()));
    }
    let mut size = PROBE_MIN_BYTES.min(head.len());
    let found = loop {
        if let Some(found) = probe_bytes(&head[..size]) {
            break Some(found);
        }
        if size == head.len() {
            break None;
        }
        size = (size * 2).min(head.len());
    };
    let Some(fmt) = found else {
        return Err(MediaError::NotVideo);
    };
    // SAFETY: a non-null probe result is a static AVInputFormat with a static name.
    let name = unsafe { CStr::from_ptr((*fmt).name) }.to_string_lossy();
    if ALLOWED_DEMUXERS.contains(&name.as_ref()) {
        return Ok(fmt);
    }
    if AUDIO_DEMUXERS.contains(&name.as_ref()) {
        return Err(MediaError::NoVideoStream);
    }
    tracing::debug!(format = %name, "refused a container outside the allow-list");
    Err(MediaError::UnsupportedContainer(name.into_owned()))
}

/// Text playlists that FFmpeg would only recognise with the right extension or enough tags
/// (a bare `#EXTM3U` media playlist, an `ffconcat` script): named here so that they are refused
/// as what they are, whatever the FFmpeg version.
fn sniff_playlist(head: &[u8]) -> Option<&'static str> {
    let text = head.strip_prefix(b"\xEF\xBB\xBF").unwrap_or(head);
    let start = text.iter().position(|b| !b.is_ascii_whitespace())?;
    let text = &text[start..];
    if text.starts_with(b"#EXTM3U") {
        Some("hls")
    } else if text.starts_with(b"ffconcat version") {
        Some("concat")
    } else {
        None
    }
}

/// FFmpeg's format detection on `data` with no file name; the demuxer when it is confident.
fn probe_bytes(data: &[u8]) -> Option<*const ffi::AVInputFormat> {
    if data.is_empty() {
        return None;
    }
    let mut buf = Vec::with_capacity(data.len() + ffi::AVPROBE_PADDING_SIZE as usize);
    buf.extend_from_slice(data);
    buf.resize(data.len() + ffi::AVPROBE_PADDING_SIZE as usize, 0);
    let name = CString::default();
    let pd = ffi::AVProbeData {
        filename: name.as_ptr(),
        buf: buf.as_mut_ptr(),
        buf_size: data.len() as c_int,
        mime_type: std::ptr::null(),
    };
    let mut score = CONFIDENT_PROBE_SCORE;
    // SAFETY: `pd` points at a zero-padded buffer that outlives the call. `is_opened = 1`
    // probes the demuxers that read from an opened file (not the AVFMT_NOFILE ones).
    let fmt = unsafe { ffi::av_probe_input_format2(&pd, 1, &mut score) };
    (!fmt.is_null()).then_some(fmt)
}

/// What FFmpeg's callbacks for one open clip point at. Boxed so the address FFmpeg holds is
/// stable while the [`Opened`] moves.
pub(crate) struct OpenGuard(#[allow(dead_code)] Box<CallbackState>);

struct CallbackState {
    interrupt: Interrupt,
    /// The one URL `io_open` may open: the upload itself.
    url: CString,
    main_opened: AtomicBool,
    /// A URL a demuxer tried to open besides the upload (refused).
    refused: Mutex<Option<String>>,
    default_io_open: IoOpen,
}

type IoOpen = Option<
    unsafe extern "C" fn(
        *mut ffi::AVFormatContext,
        *mut *mut ffi::AVIOContext,
        *const c_char,
        c_int,
        *mut *mut ffi::AVDictionary,
    ) -> c_int,
>;

/// FFmpeg's interrupt callback: polled before blocking I/O, so a cancelled or late request
/// stops even inside `avformat_open_input` / `avformat_find_stream_info`.
unsafe extern "C" fn interrupt_cb(opaque: *mut c_void) -> c_int {
    // SAFETY: `opaque` is the CallbackState owned by the OpenGuard, alive while FFmpeg can call.
    let state = unsafe { &*(opaque as *const CallbackState) };
    c_int::from(state.interrupt.check().is_err())
}

/// The format context's `io_open`, which every file open goes through, the upload's own and
/// those a demuxer makes for files it references (HLS segments, concat entries, MP4 data
/// references). Exactly one open is allowed, of the upload's URL; any other is refused and
/// remembered, so that nothing but the upload is ever read.
unsafe extern "C" fn guarded_io_open(
    s: *mut ffi::AVFormatContext,
    pb: *mut *mut ffi::AVIOContext,
    url: *const c_char,
    flags: c_int,
    options: *mut *mut ffi::AVDictionary,
) -> c_int {
    // SAFETY: nested contexts share the parent's `opaque`, our CallbackState (FFmpeg's
    // documented contract for io_open); `url` is a NUL-terminated string.
    let (state, url) = unsafe { (&*((*s).opaque as *const CallbackState), CStr::from_ptr(url)) };
    let first = !state.main_opened.swap(true, Ordering::SeqCst);
    if first && url == state.url.as_c_str() && flags & ffi::AVIO_FLAG_WRITE == 0 {
        if let Some(open) = state.default_io_open {
            // SAFETY: FFmpeg's own default, called with the arguments it was given.
            return unsafe { open(s, pb, url.as_ptr(), flags, options) };
        }
    }
    let url = url.to_string_lossy().into_owned();
    tracing::warn!(%url, "refused a file open requested by the container");
    if let Ok(mut r) = state.refused.lock() {
        r.get_or_insert(url);
    }
    ffi::AVERROR(ffi::EPERM)
}

/// Opens `path` with the demuxer `format` (never re-probed, never chosen by name), under the
/// interrupt, with `file` as the only protocol and the upload as the only file.
fn open_input(
    path: &Path,
    format: *const ffi::AVInputFormat,
    interrupt: &Interrupt,
) -> Result<(Input, OpenGuard), MediaError> {
    open_input_with(path, format, interrupt, &ALLOWED_DEMUXERS.join(","))
}

/// [`open_input`] with another `format_whitelist`, so that tests can reach the `io_open`
/// guard behind it with a demuxer that references other files.
fn open_input_with(
    path: &Path,
    format: *const ffi::AVInputFormat,
    interrupt: &Interrupt,
    format_whitelist: &str,
) -> Result<(Input, OpenGuard), MediaError> {
    // `file:` so that a path with a colon is never read as another protocol's URL.
    let mut url = b"file:".to_vec();
    url.extend_from_slice(path.as_os_str().as_bytes());
    let url = CString::new(url).map_err(|_| {
        MediaError::Io(std::io::Error::new(
            std::io::ErrorKind::InvalidInput,
            "the path contains a NUL byte",
        ))
    })?;
    // SAFETY: `format` came from FFmpeg's static demuxer table.
    let demuxer = unsafe { CStr::from_ptr((*format).name) }
        .to_string_lossy()
        .into_owned();

    // SAFETY: plain allocation; checked for null.
    let mut ps = unsafe { ffi::avformat_alloc_context() };
    if ps.is_null() {
        return Err(MediaError::Internal(
            "cannot allocate a format context".into(),
        ));
    }
    let mut state = Box::new(CallbackState {
        interrupt: interrupt.clone(),
        url: url.clone(),
        main_opened: AtomicBool::new(false),
        refused: Mutex::new(None),
        default_io_open: None,
    });
    let opaque = &mut *state as *mut CallbackState as *mut c_void;
    // SAFETY: `ps` is a fresh context; the callbacks' state lives in the returned guard,
    // which the caller keeps until after the context is closed.
    unsafe {
        state.default_io_open = (*ps).io_open;
        (*ps).opaque = opaque;
        (*ps).io_open = Some(guarded_io_open);
        (*ps).interrupt_callback = ffi::AVIOInterruptCB {
            callback: Some(interrupt_cb),
            opaque,
        };
    }
    let mut opts = ff::Dictionary::new();
    opts.set("protocol_whitelist", "file");
    opts.set("format_whitelist", format_whitelist);
    // MP4/MOV data references can point at other files; off by default, and kept off.
    opts.set("enable_drefs", "0");
    // SAFETY: the raw dictionary is handed to FFmpeg and taken back just below.
    let mut raw = unsafe { opts.disown() };
    // SAFETY: on failure avformat_open_input frees `ps` and sets it to null.
    let r = unsafe { ffi::avformat_open_input(&mut ps, url.as_ptr(), format, &mut raw) };
    // SAFETY: `raw` holds the options FFmpeg did not consume; taking it back frees them.
    drop(unsafe { ff::Dictionary::own(raw) });
    if r < 0 {
        return Err(open_error(&state, &demuxer, ff::Error::from(r)));
    }
    // SAFETY: `ps` is an opened input context.
    let r = unsafe { ffi::avformat_find_stream_info(ps, std::ptr::null_mut()) };
    if r < 0 {
        // SAFETY: closes and frees the context opened above.
        unsafe { ffi::avformat_close_input(&mut ps) };
        return Err(open_error(&state, &demuxer, ff::Error::from(r)));
    }
    // SAFETY: `ps` is opened and owned from here by the Input, which closes it on drop.
    let ictx = unsafe { Input::wrap(ps) };
    Ok((ictx, OpenGuard(state)))
}

/// Why an open failed: the interrupt first (FFmpeg reports it as a generic exit), then a
/// refused reference to another file, then the error itself. The container was detected
/// confidently, so anything about the data means a damaged file of that container.
fn open_error(state: &CallbackState, demuxer: &str, err: ff::Error) -> MediaError {
    use ff::error::{EACCES, EIO, EISDIR, ENOENT, ENOMEM, EPERM};
    if let Err(e) = state.interrupt.check() {
        return e;
    }
    if let Some(url) = state.refused.lock().ok().and_then(|r| r.clone()) {
        return MediaError::UnsupportedContainer(format!(
            "{} referencing another file ({url})",
            short_name(demuxer)
        ));
    }
    match err {
        ff::Error::Other { errno: ENOMEM } => {
            MediaError::Internal(format!("opening the clip: {err}"))
        }
        ff::Error::Other {
            errno: errno @ (EACCES | EIO | EISDIR | ENOENT | EPERM),
        } => MediaError::Io(std::io::Error::from_raw_os_error(errno)),
        _ => MediaError::Corrupt(format!("{} container: {err}", short_name(demuxer))),
    }
}

fn short_name(demuxer: &str) -> &str {
    demuxer.split(',').next().unwrap_or(demuxer)
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

#[cfg(test)]
mod tests {
    use super::*;

    /// Behind the allow-list, the `io_open` guard alone stops a demuxer that references other
    /// files: forced to open an HLS playlist naming a FIFO (opening it would block this test
    /// forever), the open fails with nothing but the upload read. (FFmpeg's concat demuxer
    /// does not pass `io_open` on to the contexts it nests, so only the allow-list stops it;
    /// `tests/hostile.rs` covers that.)
    #[test]
    fn io_open_guard_refuses_every_file_but_the_upload() {
        init().unwrap();
        let dir = tempfile::tempdir().unwrap();
        let fifo = dir.path().join("segment.ts");
        assert!(std::process::Command::new("mkfifo")
            .arg(&fifo)
            .status()
            .unwrap()
            .success());
        let cases: [(&str, String); 1] = [(
            "hls",
            format!(
                "#EXTM3U\n#EXT-X-TARGETDURATION:2\n#EXTINF:2,\nfile:{}\n#EXT-X-ENDLIST\n",
                fifo.display()
            ),
        )];
        for (demuxer, body) in cases {
            let p = dir.path().join(format!("list.{demuxer}"));
            std::fs::write(&p, body).unwrap();
            let name = CString::new(demuxer).unwrap();
            // SAFETY: lookup in FFmpeg's static demuxer table.
            let format = unsafe { ffi::av_find_input_format(name.as_ptr()) };
            assert!(!format.is_null());
            let r = open_input_with(&p, format, &Interrupt::new(), demuxer);
            let e = r.err().expect("the referenced file must not open");
            match &e {
                MediaError::UnsupportedContainer(m) => {
                    assert!(m.contains("segment.ts"), "{demuxer}: {m}")
                }
                other => panic!("{demuxer}: {other:?}"),
            }
        }
    }
}
