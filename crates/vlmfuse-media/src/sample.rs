//! The sampling engine: decode as little as possible to find the first frame at or after each
//! target time.

use ff::codec::decoder;
use ff::format::context::Input;
use ff::{frame, Discard, Packet};
use ffmpeg_next as ff;

use crate::convert::{output_size, Converter};
use crate::probe::Opened;
use crate::{
    target_times, DecodedClip, Frame, FrameSize, MediaError, SampleOptions, SampledFrame,
    MAX_OUTPUT_SIDE, MAX_SAMPLE_FRAMES,
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
    /// Video packets sent to the decoder.
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
    policy: DecodePolicy,
) -> Result<(DecodedClip, DecodeStats), MediaError> {
    let info = opened.info.clone();
    let (out_w, out_h) = output_size(opts.size, info.width, info.height);
    let total = u64::from(out_w) * u64::from(out_h) * 3 * opts.frames as u64;
    if total > MAX_OUTPUT_BYTES {
        return Err(MediaError::InvalidOptions(format!(
            "{} frames of {out_w}x{out_h} would take {} MiB, more than {} MiB",
            opts.frames,
            total >> 20,
            MAX_OUTPUT_BYTES >> 20
        )));
    }

    let mut engine = Engine::new(opened, policy)?;
    let mut converter = Converter::new(opts.size);
    let targets = target_times(info.duration_s, opts.frames);
    let mut frames: Vec<SampledFrame> = Vec::with_capacity(targets.len());
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

struct Engine {
    ictx: Input,
    decoder: decoder::Video,
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
    /// The last decoded frame and its time.
    current: Option<(f64, frame::Video)>,
    stats: DecodeStats,
}

impl Engine {
    fn new(opened: Opened, policy: DecodePolicy) -> Result<Self, MediaError> {
        let Opened {
            ictx,
            stream_index,
            info,
            time_base,
            start_pts,
            keyframes,
        } = opened;
        let st = ictx
            .stream(stream_index)
            .ok_or_else(|| MediaError::Internal("video stream vanished".into()))?;
        let mut ctx = ff::codec::context::Context::from_parameters(st.parameters())
            .map_err(|e| MediaError::Internal(format!("decoder parameters: {e}")))?;
        let threads = std::thread::available_parallelism().map_or(1, |n| n.get().min(8));
        ctx.set_threading(ff::threading::Config {
            kind: ff::threading::Type::Frame,
            count: threads,
            ..Default::default()
        });
        let decoder = ctx.decoder().video().map_err(|e| match e {
            ff::Error::DecoderNotFound => MediaError::UnsupportedCodec(info.codec.clone()),
            e => MediaError::Corrupt(format!("cannot open the {} decoder: {e}", info.codec)),
        })?;
        // Without an index, keyframes are learnt from the packets read (for intra-only codecs
        // every packet is one, so seeking quickly looks cheap, as it is).
        let indexed = !keyframes.is_empty();
        Ok(Engine {
            ictx,
            decoder,
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
        match self.ictx.seek(ts_us, ..ts_us) {
            Ok(()) => {
                self.decoder.flush();
                self.read_pos = None;
                self.after_seek = true;
                self.stats.seeks += 1;
            }
            Err(e) => {
                tracing::debug!(error = %e, target, "seek failed; decoding forward instead");
                self.no_seek = true;
            }
        }
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
                Err(ff::Error::Eof) => return Ok(None),
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
                return Ok(None);
            }
            self.feed(target)?;
        }
    }

    /// Sends the next video packet to the decoder, or signals the end of input.
    fn feed(&mut self, target: Option<f64>) -> Result<(), MediaError> {
        let mut packet = Packet::empty();
        loop {
            match packet.read(&mut self.ictx) {
                Ok(()) => {}
                Err(ff::Error::Eof) => return self.end_of_input(None),
                Err(ff::Error::InvalidData) => {
                    self.decode_error(ff::Error::InvalidData)?;
                    continue;
                }
                Err(e) => return self.end_of_input(Some(e.to_string())),
            }
            if packet.stream() != self.stream_index {
                continue;
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

    fn decode_error(&mut self, e: ff::Error) -> Result<(), MediaError> {
        self.stats.decode_errors += 1;
        if self.stats.decode_errors > MAX_DECODE_ERRORS {
            return Err(MediaError::Corrupt(format!(
                "more than {MAX_DECODE_ERRORS} corrupt packets (last: {e})"
            )));
        }
        Ok(())
    }
}
