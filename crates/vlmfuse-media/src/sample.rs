//! The sampling engine: decode as little as possible to find the first frame at or after each
//! target time.

use ff::codec::decoder;
use ff::format::context::Input;
use ff::{ffi, frame, Discard, Packet};
use ffmpeg_next as ff;
use std::ffi::{c_int, c_void};
use std::sync::atomic::{AtomicU64, Ordering};

use crate::convert::{output_size, Converter};
use crate::probe::{OpenGuard, Opened};
use crate::{
    target_times, DecodedClip, Frame, FrameSize, Interrupt, MediaError, MediaLimits, SampleOptions,
    SampledFrame, MAX_OUTPUT_SIDE, MAX_SAMPLE_FRAMES,
};

/// How [`crate::sample_frames_with_policy`] walks through the clip. All policies return the
/// same frames; they differ only in cost, which is why they exist side by side (benchmarks,
/// and tests that check the clever path against the naive one).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum DecodePolicy {
    /// Seek when the container index shows a keyframe far enough past the decoder's position
    /// that jumping to it skips work; otherwise decode forward. The default.
    #[default]
    Auto,
    /// Never seek; decode in order and stop after the last target. Wins on short clips and on
    /// clips with one keyframe, where every seek lands back at the start.
    Forward,
    /// Seek before every target that is ahead of the decoder. Wins on long clips with
    /// frequent keyframes.
    Seek,
    /// Decode every frame of the clip (the naive baseline for benchmarks).
    Everything,
}

/// Counters of the work one sampling run did, so benchmarks and tests can tell a cheap run
/// from an expensive one without timing it.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct DecodeStats {
    /// Video packets sent to the decoder: the decode work, bounded by
    /// [`crate::MediaLimits::max_frames_decoded`].
    pub packets: u64,
    /// Frames the decoder returned (frames it was allowed to drop are not counted).
    pub frames_decoded: u64,
    /// Seeks performed.
    pub seeks: u64,
    /// Packets or frames the decoder rejected as corrupt and that were skipped.
    pub decode_errors: u64,
}

/// Above this many skipped corrupt packets/frames the clip is declared corrupt: a few bad
/// packets are common in dashcam files cut at power-off, thousands mean garbage.
const MAX_DECODE_ERRORS: u64 = 256;

/// All requested frames together may not exceed this many bytes of RGB.
const MAX_OUTPUT_BYTES: u64 = 1 << 30;

/// A seek costs about this many frames of forward decoding (flush, refilling the decoder's
/// thread pipeline); a seek that skips fewer frames than this is not worth it.
const SEEK_COST_FRAMES: f64 = 8.0;

/// Without an index or an observed keyframe spacing, seek only when the target is at least this
/// far ahead.
const BLIND_SEEK_GAP_S: f64 = 2.0;

/// Slack when comparing a frame's time with a target: frame times are exact rationals, the
/// targets are floats.
const EPS: f64 = 1e-6;

pub(crate) fn validate_options(opts: &SampleOptions) -> Result<(), MediaError> {
    if opts.frames == 0 || opts.frames > MAX_SAMPLE_FRAMES {
        return Err(MediaError::InvalidOptions(format!(
            "frames must be between 1 and {MAX_SAMPLE_FRAMES}, got {}",
            opts.frames
        )));
    }
    let ok = |v: u32| (1..=MAX_OUTPUT_SIDE).contains(&v);
    let valid = match opts.size {
        FrameSize::Native => true,
        FrameSize::ShortSide(n) => ok(n),
        FrameSize::Exact { width, height } => ok(width) && ok(height),
    };
    if !valid {
        return Err(MediaError::InvalidOptions(format!(
            "frame sides must be between 1 and {MAX_OUTPUT_SIDE}, got {:?}",
            opts.size
        )));
    }
    Ok(())
}

pub(crate) fn run(
    opened: Opened,
    opts: &SampleOptions,
    limits: &MediaLimits,
    policy: DecodePolicy,
    interrupt: &Interrupt,
) -> Result<(DecodedClip, DecodeStats), MediaError> {
    let targets = target_times(opened.info.duration_s, opts.frames);
    run_at(opened, &targets, opts.size, limits, policy, interrupt)
}

/// Samples the first frame at or after each of `targets` (seconds, ascending), as
/// [`run`] does for its uniform targets.
pub(crate) fn run_at(
    opened: Opened,
    targets: &[f64],
    size: FrameSize,
    limits: &MediaLimits,
    policy: DecodePolicy,
    interrupt: &Interrupt,
) -> Result<(DecodedClip, DecodeStats), MediaError> {
    let opts = SampleOptions {
        frames: targets.len(),
        size,
    };
    let opts = &opts;
    let info = opened.info.clone();
    let (out_w, out_h) = output_size(opts.size, info.width, info.height);
    let total = u64::from(out_w) * u64::from(out_h) * 3 * opts.frames as u64;
    if total > MAX_OUTPUT_BYTES {
        return Err(too_many_bytes(opts.frames, total));
    }
    if opened.complete_index {
        let frames = min_decodes(targets, &opened.keyframes, info.fps);
        if frames > limits.max_frames_decoded {
            return Err(MediaError::TooManyFrames {
                frames,
                max_frames: limits.max_frames_decoded,
            });
        }
    }

    let mut engine = Engine::new(opened, limits, policy, interrupt)?;
    let mut converter = Converter::new(opts.size);
    let mut frames: Vec<SampledFrame> = Vec::with_capacity(targets.len());
    let mut out_bytes = 0u64;
    for (index, &target) in targets.iter().enumerate() {
        let pts = engine.advance_to(target, info.duration_s)?;
        let previous = frames.last().filter(|f| f.pts_s == pts);
        let frame = match previous {
            // The same picture answers two targets (more targets than frames): skip the
            // conversion.
            Some(prev) => SampledFrame {
                index,
                target_s: target,
                frame: prev.frame.clone(),
            },
            None => {
                let Some((_, picture)) = engine.current.as_ref() else {
                    return Err(MediaError::Internal("no current frame".into()));
                };
                let (width, height, rgb) = converter.convert(picture)?;
                // The header's size was checked above; the stream may have grown since.
                out_bytes += rgb.len() as u64;
                if out_bytes > MAX_OUTPUT_BYTES {
                    let per_frame = rgb.len() as u64;
                    return Err(too_many_bytes(opts.frames, per_frame * opts.frames as u64));
                }
                SampledFrame {
                    index,
                    target_s: target,
                    frame: Frame {
                        width,
                        height,
                        rgb,
                        pts_s: pts,
                    },
                }
            }
        };
        frames.push(frame);
    }
    if policy == DecodePolicy::Everything {
        while engine.next_frame(None)?.is_some() {}
    }
    tracing::debug!(stats = ?engine.stats, ?policy, "sampled clip");
    Ok((DecodedClip { info, frames }, engine.stats))
}

fn too_many_bytes(frames: usize, total: u64) -> MediaError {
    MediaError::InvalidOptions(format!(
        "{frames} frames of this clip would take {} MiB of RGB, more than {} MiB",
        total >> 20,
        MAX_OUTPUT_BYTES >> 20
    ))
}

/// A lower bound of the packets any strategy must decode to sample `targets`, from a complete
/// keyframe index: reaching the frame at `t_j` means decoding forward from the previous target
/// or from the last keyframe at or before `t_j`, whichever is later. A bound rather than an
/// estimate, so that no clip the decoder could sample within the budget is refused.
fn min_decodes(targets: &[f64], keyframes: &[f64], fps: f64) -> u64 {
    if fps <= 0.0 || keyframes.is_empty() {
        return 0;
    }
    let mut previous = f64::NEG_INFINITY;
    let mut total = 0.0;
    for &t in targets {
        let i = keyframes.partition_point(|&k| k <= t + EPS);
        let key = i.checked_sub(1).map_or(0.0, |i| keyframes[i]);
        let from = key.max(previous);
        if t > from {
            total += ((t - from) * fps - 1.0).max(0.0).floor();
        }
        previous = previous.max(t);
    }
    total as u64
}

/// The limits as the decoder's buffer callback sees them, and the first picture size it refused.
struct SizeGuard {
    /// (long side, short side), orientation-agnostic like the header check.
    max_sides: (u32, u32),
    /// `width << 32 | height` of the first refused picture; 0 while none was.
    oversized: AtomicU64,
}

/// The decoder's `get_buffer2`: refuses to allocate a picture larger than the limits (the
/// decode of that frame fails, and the engine reports why), else FFmpeg's default allocator.
/// Called from the decoder's frame threads, hence only atomics in the shared state.
unsafe extern "C" fn guarded_get_buffer2(
    s: *mut ffi::AVCodecContext,
    frame: *mut ffi::AVFrame,
    flags: c_int,
) -> c_int {
    // SAFETY: `opaque` is the SizeGuard owned by the Engine, copied into every frame-thread
    // context; `s` and `frame` are live for the duration of the call.
    unsafe {
        let guard = &*((*s).opaque as *const SizeGuard);
        let (mut w, mut h) = ((*s).width, (*s).height);
        if w <= 0 || h <= 0 {
            (w, h) = ((*frame).width, (*frame).height);
        }
        let (w, h) = (w.max(0) as u32, h.max(0) as u32);
        if w.max(h) > guard.max_sides.0 || w.min(h) > guard.max_sides.1 {
            let packed = (u64::from(w) << 32) | u64::from(h);
            let _ =
                guard
                    .oversized
                    .compare_exchange(0, packed, Ordering::Relaxed, Ordering::Relaxed);
            return ffi::AVERROR(ffi::EINVAL);
        }
        ffi::avcodec_default_get_buffer2(s, frame, flags)
    }
}

struct Engine {
    ictx: Input,
    /// Keeps FFmpeg's callback state alive; after `ictx` so it is dropped after it.
    _guard: OpenGuard,
    decoder: decoder::Video,
    /// What the decoder's `get_buffer2` reads; after `decoder` so it is dropped after it.
    size_guard: Box<SizeGuard>,
    interrupt: Interrupt,
    /// Orientation-agnostic picture bounds (long side, short side) every frame must meet.
    max_sides: (u32, u32),
    limits_wh: (u32, u32),
    max_packets: u64,
    stream_index: usize,
    time_base: f64,
    start_pts: i64,
    fps: f64,
    policy: DecodePolicy,
    /// Known keyframe times (seconds from the stream start), sorted.
    keyframes: Vec<f64>,
    /// Whether `keyframes` came from the container's index, which then says exactly where a
    /// seek can land; otherwise it holds only the keyframes seen so far.
    indexed: bool,
    /// Largest time of a video packet sent to the decoder since the last seek.
    read_pos: Option<f64>,
    /// The demuxer reached the end (or a read error) and the decoder was told so.
    demux_done: bool,
    read_error: Option<String>,
    /// Seeking failed once or timestamps are missing: decode forward only from then on.
    no_seek: bool,
    /// The decoder currently drops non-reference frames.
    skipping: bool,
    /// The next decoded frame is the first after a seek.
    after_seek: bool,
    /// A frame was decoded since the last seek (or since the start).
    decoded_since_seek: bool,
    /// The last decoded frame and its time.
    current: Option<(f64, frame::Video)>,
    stats: DecodeStats,
}

impl Engine {
    fn new(
        opened: Opened,
        limits: &MediaLimits,
        policy: DecodePolicy,
        interrupt: &Interrupt,
    ) -> Result<Self, MediaError> {
        let Opened {
            ictx,
            guard,
            stream_index,
            info,
            time_base,
            start_pts,
            keyframes,
            complete_index: _,
        } = opened;
        let st = ictx
            .stream(stream_index)
            .ok_or_else(|| MediaError::Internal("video stream vanished".into()))?;
        let mut ctx = ff::codec::context::Context::from_parameters(st.parameters())
            .map_err(|e| MediaError::Internal(format!("decoder parameters: {e}")))?;
        let threads = match limits.decode_threads {
            0 => std::thread::available_parallelism().map_or(1, |n| n.get().min(8)),
            n => n,
        };
        ctx.set_threading(ff::threading::Config {
            kind: ff::threading::Type::Frame,
            count: threads,
            ..Default::default()
        });
        let max_sides = (
            limits.max_width.max(limits.max_height),
            limits.max_width.min(limits.max_height),
        );
        // Every picture the decoder allocates (outputs, references, one per frame thread) is
        // checked against the limits before the allocation, so a stream that switches to 16k x
        // 16k midway costs nothing, and the refusal can name the size.
        let mut size_guard = Box::new(SizeGuard {
            max_sides,
            oversized: AtomicU64::new(0),
        });
        // SAFETY: setting plain fields of the codec context before it is opened; the guard is
        // boxed (stable address) and kept in the Engine after the decoder, so it outlives it
        // and the frame-thread copies of the context that share `opaque`.
        unsafe {
            let c = ctx.as_mut_ptr();
            (*c).opaque = &mut *size_guard as *mut SizeGuard as *mut c_void;
            (*c).get_buffer2 = Some(guarded_get_buffer2);
        }
        let decoder = ctx.decoder().video().map_err(|e| match e {
            ff::Error::DecoderNotFound => MediaError::UnsupportedCodec(info.codec.clone()),
            e => MediaError::Corrupt(format!("cannot open the {} decoder: {e}", info.codec)),
        })?;
        // Without an index, keyframes are learnt from the packets read (for intra-only codecs
        // every packet is one, so seeking quickly looks cheap, as it is).
        let indexed = !keyframes.is_empty();
        Ok(Engine {
            ictx,
            _guard: guard,
            decoder,
            size_guard,
            interrupt: interrupt.clone(),
            max_sides,
            limits_wh: (limits.max_width, limits.max_height),
            max_packets: limits.max_frames_decoded,
            stream_index,
            time_base,
            start_pts,
            fps: info.fps,
            policy,
            keyframes,
            indexed,
            read_pos: None,
            demux_done: false,
            read_error: None,
            no_seek: false,
            skipping: false,
            after_seek: false,
            decoded_since_seek: false,
            current: None,
            stats: DecodeStats::default(),
        })
    }

    fn frame_duration(&self) -> f64 {
        if self.fps > 0.0 {
            1.0 / self.fps
        } else {
            1.0 / 30.0
        }
    }

    /// Makes `current` the first frame at or after `target` (or the last frame of the clip)
    /// and returns its time.
    fn advance_to(&mut self, target: f64, duration: f64) -> Result<f64, MediaError> {
        if let Some((pts, _)) = &self.current {
            // `current` is the first frame at or after an earlier target; if it is also past
            // this one, every frame before it is earlier than this target too.
            if *pts >= target - EPS {
                return Ok(*pts);
            }
        }
        if self.should_seek(target) {
            self.seek(target, self.preroll());
        }
        let mut reseeked = false;
        loop {
            let after_seek = std::mem::take(&mut self.after_seek);
            match self.next_frame(Some(target))? {
                Some((pts, picture)) => {
                    if after_seek && pts > target + EPS && !reseeked && !self.no_seek {
                        // The seek landed past the target (an imprecise index): frames between
                        // the target and here may be missing. Go back further, once.
                        reseeked = true;
                        self.seek(target, 2.0 * (pts - target) + 1.0);
                        continue;
                    }
                    self.current = Some((pts, picture));
                    if pts >= target - EPS {
                        return Ok(pts);
                    }
                }
                None if !self.decoded_since_seek && !self.no_seek && self.stats.seeks > 0 => {
                    // The seek landed where nothing decodes until the end (no keyframe after
                    // it: an unindexed stream with a single keyframe). Rewind to the start and
                    // decode forward from there, without seeking again.
                    tracing::debug!(target, "no frame after a seek; decoding from the start");
                    self.seek(0.0, 0.0);
                    self.no_seek = true;
                    self.demux_done = false;
                    self.read_error = None;
                }
                None => {
                    let Some((pts, _)) = &self.current else {
                        return Err(MediaError::Corrupt(match &self.read_error {
                            Some(e) => format!("no decodable video frame ({e})"),
                            None => "no decodable video frame".into(),
                        }));
                    };
                    // The clip ended before the target. A little is normal (the container's
                    // duration overshoots the last frame); a lot means the file was cut.
                    let tolerance = (0.1 * duration).max(1.0);
                    if target - pts > tolerance {
                        return Err(MediaError::Corrupt(format!(
                            "video data ends at {pts:.2} s but the header says {duration:.2} s{}",
                            self.read_error
                                .as_ref()
                                .map(|e| format!(" ({e})"))
                                .unwrap_or_default()
                        )));
                    }
                    return Ok(*pts);
                }
            }
        }
    }

    /// How far before a target to aim a seek, so that frames shown just before the keyframe
    /// we land on (reordered B-frames; indexes that store decode times) are not skipped.
    fn preroll(&self) -> f64 {
        3.0 * self.frame_duration()
    }

    fn should_seek(&self, target: f64) -> bool {
        if self.demux_done || self.no_seek {
            return false;
        }
        let pos = self.read_pos.unwrap_or(0.0);
        match self.policy {
            DecodePolicy::Forward | DecodePolicy::Everything => false,
            DecodePolicy::Seek => target - pos > self.preroll() + self.frame_duration(),
            DecodePolicy::Auto => {
                let margin = SEEK_COST_FRAMES * self.frame_duration();
                let seek_to = target - self.preroll();
                let landing = self
                    .keyframes
                    .partition_point(|&k| k <= seek_to)
                    .checked_sub(1)
                    .map(|i| self.keyframes[i]);
                if self.indexed {
                    // The index is where a seek lands: seek only if that skips enough frames.
                    return landing.is_some_and(|k| k > pos + margin);
                }
                // No index: guess from the keyframe spacing seen so far.
                let spacing = match self.keyframes.len() {
                    0 | 1 => None,
                    n => Some((self.keyframes[n - 1] - self.keyframes[0]) / (n - 1) as f64),
                };
                let gap = target - pos;
                match spacing {
                    Some(s) => gap > s + margin,
                    None => gap > BLIND_SEEK_GAP_S,
                }
            }
        }
    }

    /// Seeks to the keyframe at or before `target - preroll`. A failed seek is not an error:
    /// decoding forward still finds the frame, only slower.
    fn seek(&mut self, target: f64, preroll: f64) {
        let t = (target - preroll).max(0.0);
        let ts = self.start_pts as f64 * self.time_base + t;
        let ts_us = (ts * 1e6).floor();
        if !ts_us.is_finite() || ts_us.abs() > 9e15 {
            self.no_seek = true;
            return;
        }
        let ts_us = ts_us as i64;
        let result = if t <= 0.0 {
            self.rewind()
        } else {
            self.ictx.seek(ts_us, ..ts_us)
        };
        match result {
            Ok(()) => {
                self.decoder.flush();
                self.read_pos = None;
                self.after_seek = true;
                self.decoded_since_seek = false;
                self.stats.seeks += 1;
            }
            Err(e) => {
                tracing::debug!(error = %e, target, "seek failed; decoding forward instead");
                self.no_seek = true;
            }
        }
    }

    /// Back to the first packet. A byte seek to offset 0 where the container allows one: a
    /// timestamp seek to the start can land on a later keyframe in streams without an index
    /// (MPEG-TS with B-frames, whose first keyframe's decode time precedes the start time).
    fn rewind(&mut self) -> Result<(), ff::Error> {
        // SAFETY: reading the static demuxer description of an open context.
        let byte_seekable =
            unsafe { (*(*self.ictx.as_ptr()).iformat).flags } & ffi::AVFMT_NO_BYTE_SEEK == 0;
        if byte_seekable {
            // SAFETY: seeking an open context; byte offsets 0..=0.
            let r = unsafe {
                ffi::avformat_seek_file(self.ictx.as_mut_ptr(), -1, 0, 0, 0, ffi::AVSEEK_FLAG_BYTE)
            };
            if r >= 0 {
                return Ok(());
            }
        }
        let start = (self.start_pts as f64 * self.time_base * 1e6).floor() as i64;
        self.ictx.seek(start, ..start)
    }

    fn seconds(&self, ticks: i64) -> f64 {
        ticks.saturating_sub(self.start_pts) as f64 * self.time_base
    }

    /// The next frame in display order, or `None` at the end of the clip. With a `target`,
    /// the decoder may drop non-reference frames shown before it.
    fn next_frame(
        &mut self,
        target: Option<f64>,
    ) -> Result<Option<(f64, frame::Video)>, MediaError> {
        loop {
            let mut picture = frame::Video::empty();
            match self.decoder.receive_frame(&mut picture) {
                Ok(()) => {
                    self.stats.frames_decoded += 1;
                    self.decoded_since_seek = true;
                    self.check_size(&picture)?;
                    let pts = match picture.timestamp().or(picture.pts()) {
                        Some(t) => self.seconds(t),
                        None => {
                            // No timestamps at all: count frames, and stop seeking, since
                            // positions after a seek would be unknown.
                            self.no_seek = true;
                            self.current
                                .as_ref()
                                .map_or(0.0, |(p, _)| p + self.frame_duration())
                        }
                    };
                    return Ok(Some((pts, picture)));
                }
                Err(ff::Error::Eof) => {
                    self.refused_picture()?;
                    return Ok(None);
                }
                Err(ff::Error::Other {
                    errno: ff::error::EAGAIN,
                }) => {}
                Err(e) => {
                    self.decode_error(e)?;
                    continue;
                }
            }
            if self.demux_done {
                // The decoder was told the input ended yet wants more: nothing more will come.
                self.refused_picture()?;
                return Ok(None);
            }
            self.feed(target)?;
        }
    }

    /// The limits hold for every picture, not only the header's: a stream may switch to a
    /// larger resolution midway (concatenated MPEG-TS, adaptive streams).
    fn check_size(&self, picture: &frame::Video) -> Result<(), MediaError> {
        let (w, h) = (picture.width(), picture.height());
        if w.max(h) > self.max_sides.0 || w.min(h) > self.max_sides.1 {
            return Err(MediaError::ResolutionTooHigh {
                width: w,
                height: h,
                max_width: self.limits_wh.0,
                max_height: self.limits_wh.1,
            });
        }
        Ok(())
    }

    /// Sends the next video packet to the decoder, or signals the end of input.
    fn feed(&mut self, target: Option<f64>) -> Result<(), MediaError> {
        let mut packet = Packet::empty();
        loop {
            self.interrupt.check()?;
            match packet.read(&mut self.ictx) {
                Ok(()) => {}
                Err(ff::Error::Eof) => return self.end_of_input(None),
                Err(ff::Error::InvalidData) => {
                    self.decode_error(ff::Error::InvalidData)?;
                    continue;
                }
                Err(e) => {
                    // An interrupted read is not the end of the clip.
                    self.interrupt.check()?;
                    return self.end_of_input(Some(e.to_string()));
                }
            }
            if packet.stream() != self.stream_index {
                continue;
            }
            if self.stats.packets >= self.max_packets {
                return Err(MediaError::TooManyFrames {
                    frames: self.stats.packets + 1,
                    max_frames: self.max_packets,
                });
            }
            self.stats.packets += 1;
            let time = packet.pts().or(packet.dts()).map(|t| self.seconds(t));
            if let Some(t) = time {
                self.read_pos = Some(self.read_pos.map_or(t, |r| r.max(t)));
                if packet.is_key() && !self.indexed {
                    let i = self.keyframes.partition_point(|&k| k < t);
                    if self.keyframes.get(i) != Some(&t) {
                        self.keyframes.insert(i, t);
                    }
                }
            }
            // A frame shown before the target is never returned, so if nothing references it
            // the decoder need not decode it at all (B-frames).
            let skip = self.policy != DecodePolicy::Everything
                && matches!((target, time), (Some(tg), Some(t)) if t < tg - EPS);
            if skip != self.skipping {
                self.decoder.skip_frame(if skip {
                    Discard::NonReference
                } else {
                    Discard::Default
                });
                self.skipping = skip;
            }
            return match self.decoder.send_packet(&packet) {
                Ok(()) => Ok(()),
                Err(e) => self.decode_error(e),
            };
        }
    }

    fn end_of_input(&mut self, error: Option<String>) -> Result<(), MediaError> {
        if let Some(e) = &error {
            tracing::debug!(error = %e, "read error; treating as end of clip");
        }
        self.read_error = error;
        self.demux_done = true;
        if self.skipping {
            self.decoder.skip_frame(Discard::Default);
            self.skipping = false;
        }
        // An error here only means the decoder had already been told.
        let _ = self.decoder.send_eof();
        Ok(())
    }

    /// `Err(ResolutionTooHigh)` once the decoder's buffer callback refused a picture.
    fn refused_picture(&self) -> Result<(), MediaError> {
        match self.size_guard.oversized.load(Ordering::Relaxed) {
            0 => Ok(()),
            packed => Err(MediaError::ResolutionTooHigh {
                width: (packed >> 32) as u32,
                height: packed as u32,
                max_width: self.limits_wh.0,
                max_height: self.limits_wh.1,
            }),
        }
    }

    fn decode_error(&mut self, e: ff::Error) -> Result<(), MediaError> {
        self.refused_picture()?;
        self.stats.decode_errors += 1;
        if self.stats.decode_errors > MAX_DECODE_ERRORS {
            return Err(MediaError::Corrupt(format!(
                "more than {MAX_DECODE_ERRORS} corrupt packets (last: {e})"
            )));
        }
        Ok(())
    }
}
