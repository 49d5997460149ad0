//! A cheap pre-scan of MP4/MOV sample tables, run before FFmpeg opens the upload.
//!
//! FFmpeg's mov demuxer allocates per *declared* entry when it reads a sample table: `stsz`'s
//! sample count becomes one 24-byte index entry per sample, and `stts`, `ctts`, `stss`, `stsc`,
//! `stco`, `co64`, `elst`, `sbgp`, `tfra` and every fragment's `trun` allocate their entry
//! counts before reading a single entry. A 3 KB file that declares 80 million samples therefore
//! costs gigabytes of memory before anything says it is broken. This scan walks the box tree
//! (`moov` → `trak` → `mdia` → `minf` → `stbl`, `edts`, and the fragments' `moof` → `traf`,
//! plus `mfra`), reads only box headers and the counts at the start of those tables, and
//! refuses the file when:
//!
//! * a table declares more entries than its own box has bytes for (each `stsz` size is 4
//!   bytes, each `stts` entry 8, ...): the count is then a lie, and the only one that costs;
//! * the samples declared across the file's tracks (`stsz` counts and `trun` counts, which can
//!   be large for free: a constant sample size or a `trun` without per-sample fields needs no
//!   bytes per sample) exceed [`sample_limit`], derived from the longest clip accepted;
//! * any table declares more entries than that limit (a table has at most one entry per
//!   sample or chunk);
//! * the box sizes are inconsistent inside the index (a size under the header's, a child that
//!   overruns its parent): FFmpeg would clamp and carry on, reading the rest as garbage.
//!
//! FFmpeg reads a table wherever its generic box reader meets one, not only in `stbl`, and the
//! last one read wins; so the scan also walks the containers FFmpeg walks that way (`udta`,
//! `meta`, `dinf`, ..., leniently: their sizes are handled as FFmpeg handles them and never
//! refuse a file), looks for tables by name inside sample descriptions (`stsd`), whose
//! extension boxes FFmpeg reads the same way, and refuses compressed headers (`cmov`), which
//! it cannot see into.
//!
//! The scan's own work is bounded: at most [`MAX_BOXES`] boxes and [`MAX_DEPTH`] levels; the
//! only bytes it reads beyond headers and counts are the `stsc` runs (at most
//! [`sample_limit`] entries in all) and sample descriptions and `meta` heads (at most
//! [`MAX_SEARCHED_BYTES`] each, [`MAX_SEARCHED_TOTAL`] in all).

use std::fs::File;
use std::io::{BufReader, Read, Seek};
use std::path::Path;

use crate::{MediaError, MediaLimits};

/// The most boxes one scan visits. A fragmented clip with one fragment per frame at 240 fps for
/// the default two minutes has about 230,000 (`moof`, `mfhd`, `traf`, `tfhd`, `tfdt`, `trun`,
/// `mdat`, `sdtp` per frame); beyond this the file is refused rather than walked.
pub(crate) const MAX_BOXES: u64 = 500_000;

/// The deepest nesting the scan follows. The deepest box it reads is at depth 6
/// (`moov/trak/mdia/minf/stbl/stsz`); the margin is for containers it does not descend.
pub(crate) const MAX_DEPTH: u32 = 12;

/// Samples per second of clip that the sample limit allows. The crate already treats a frame
/// rate of 1000 or more as nonsense (see `probe::open`), and every real track is far below:
/// 240 fps slow-motion video, 47 AAC frames per second at 48 kHz.
pub(crate) const MAX_SAMPLES_PER_SECOND: f64 = 1000.0;

/// The most bytes of a `stsd` or of the head of a `meta` that the scan reads to find the
/// boxes inside (a sample description is a few hundred bytes).
const MAX_SEARCHED_BYTES: u64 = 1 << 20;

/// The most bytes all those whole reads of one file may add up to (nested `meta` boxes read
/// overlapping heads).
const MAX_SEARCHED_TOTAL: u64 = 8 << 20;

/// The boxes looked for inside sample descriptions, with the fewest payload bytes each needs
/// to be read: those that allocate by a declared count, `hdlr` (it decides how a track is
/// indexed) and `cmov`.
const RAW_SCANNED: [(&[u8; 4], u64); 15] = [
    (b"stsz", 12),
    (b"stz2", 12),
    (b"stts", 8),
    (b"ctts", 8),
    (b"stss", 8),
    (b"stps", 8),
    (b"stco", 8),
    (b"co64", 8),
    (b"stsc", 8),
    (b"elst", 8),
    (b"sbgp", 12),
    (b"trun", 8),
    (b"tfra", 16),
    (b"hdlr", 12),
    (b"cmov", 0),
];

/// Bounds of [`sample_limit`]: at least this many, so that very short duration limits do not
/// refuse ordinary clips whose header runs slightly long ...
const MIN_SAMPLE_LIMIT: u64 = 10_000;
/// ... and at most this many, so that the index FFmpeg builds (about 24 bytes per sample, plus
/// the tables' own entries) stays within ~64 MB whatever `max_duration_s` says.
const MAX_SAMPLE_LIMIT: u64 = 2_000_000;

/// Uncompressed audio (`soun` tracks with one `stts` entry of duration 1) is indexed by chunk,
/// not by sample, and each PCM sample is at least one byte of the file; ADPCM packs a few
/// samples per byte. The samples such a track's `stsc` implies may therefore be at most this
/// many per byte of the file.
const MAX_CHUNKED_SAMPLES_PER_BYTE: u64 = 8;

/// The most samples (and entries of any one table) a file may declare under `limits`:
/// `max_duration_s` × [`MAX_SAMPLES_PER_SECOND`], within [`MIN_SAMPLE_LIMIT`] and
/// [`MAX_SAMPLE_LIMIT`]. With the default two minutes: 120,000.
pub(crate) fn sample_limit(limits: &MediaLimits) -> u64 {
    let d = limits.max_duration_s;
    if !(d.is_finite() && d > 0.0) {
        return MAX_SAMPLE_LIMIT;
    }
    // `as` saturates; the clamp handles both ends.
    ((d * MAX_SAMPLES_PER_SECOND).ceil() as u64).clamp(MIN_SAMPLE_LIMIT, MAX_SAMPLE_LIMIT)
}

/// Scans the MP4/MOV file at `path` (of `len` bytes); see the module documentation.
pub(crate) fn check(path: &Path, len: u64, limits: &MediaLimits) -> Result<(), MediaError> {
    let file = File::open(path)?;
    check_reader(BufReader::with_capacity(16 * 1024, file), len, limits)
}

/// [`check`] on any seekable reader holding `len` bytes.
pub(crate) fn check_reader<R: Read + Seek>(
    reader: BufReader<R>,
    len: u64,
    limits: &MediaLimits,
) -> Result<(), MediaError> {
    let mut scan = Scanner {
        src: Source { r: reader, pos: 0 },
        file_len: len,
        limit: sample_limit(limits),
        boxes: 0,
        samples: 0,
        searched: 0,
        stsc_read: 0,
    };
    scan.children(0, len, 0, true, Parent::File, &mut Track::default())
}

/// Reads with a known position, so that skipping a box is a relative seek that keeps the
/// buffer when the next box is already in it.
struct Source<R> {
    r: BufReader<R>,
    pos: u64,
}

impl<R: Read + Seek> Source<R> {
    fn read_at(&mut self, at: u64, buf: &mut [u8]) -> Result<(), MediaError> {
        if at != self.pos {
            let delta = i64::try_from(at)
                .ok()
                .zip(i64::try_from(self.pos).ok())
                .map(|(a, p)| a - p)
                .ok_or_else(|| MediaError::Corrupt("box offset out of range".into()))?;
            self.r.seek_relative(delta)?;
            self.pos = at;
        }
        self.r.read_exact(buf).map_err(|e| match e.kind() {
            // Only if the file shrank after its size was taken: every read is inside a box
            // already checked against that size.
            std::io::ErrorKind::UnexpectedEof => {
                MediaError::Corrupt("the file ends inside a box".into())
            }
            _ => MediaError::Io(e),
        })?;
        self.pos += buf.len() as u64;
        Ok(())
    }
}

/// Whether the boxes being walked are the file's top level, where a box cut off by the end of
/// the file is a cut recording rather than a broken index.
#[derive(Clone, Copy, PartialEq, Eq)]
enum Parent {
    File,
    Other,
}

/// What one `trak` declares, judged once the whole track is read (its boxes come in any order).
#[derive(Default)]
struct Track {
    /// False for the stand-in that collects tables found outside any `trak`.
    in_trak: bool,
    /// The last handler that sets the media type (`vide`, `soun`, ...).
    handler: [u8; 4],
    /// `stsz`/`stz2` sample count.
    samples: Option<u64>,
    stts_entries: u64,
    /// The duration of the single `stts` entry, when there is exactly one.
    stts_single_delta: Option<u32>,
    /// `stco`/`co64` entry count.
    chunks: u64,
    /// `stsc` runs: (first chunk, 1-based; samples per chunk).
    stsc: Vec<(u32, u32)>,
}

struct Scanner<R> {
    src: Source<R>,
    file_len: u64,
    limit: u64,
    boxes: u64,
    /// Samples declared so far by sample-indexed tracks and fragments.
    samples: u64,
    /// Bytes read whole so far (sample descriptions, heads of `meta`), against
    /// [`MAX_SEARCHED_TOTAL`].
    searched: u64,
    /// `stsc` entries read so far, against the sample limit: each track has at most one per
    /// chunk, but the same bytes can be reached as many boxes from inside a description.
    stsc_read: u64,
}

impl<R: Read + Seek> Scanner<R> {
    /// Reads `[at, at + len)` whole, within the scan's budget of such reads.
    fn read_whole(&mut self, at: u64, len: u64) -> Result<Vec<u8>, MediaError> {
        self.searched = self.searched.saturating_add(len);
        if self.searched > MAX_SEARCHED_TOTAL {
            return Err(MediaError::Corrupt(format!(
                "the MP4's sample descriptions and metadata headers exceed \
                 {MAX_SEARCHED_TOTAL} bytes"
            )));
        }
        let mut data = vec![0u8; len as usize];
        self.src.read_at(at, &mut data)?;
        Ok(data)
    }
}

fn fourcc(kind: &[u8; 4]) -> String {
    kind.iter()
        .map(|&b| {
            if b.is_ascii_graphic() {
                char::from(b)
            } else {
                '?'
            }
        })
        .collect()
}

fn be32(b: &[u8]) -> u32 {
    u32::from_be_bytes([b[0], b[1], b[2], b[3]])
}

fn too_many(table: &'static str, declared: u64, limit: u64) -> MediaError {
    MediaError::TooManySamples {
        table,
        declared,
        limit,
    }
}

impl<R: Read + Seek> Scanner<R> {
    /// Walks the boxes in `[start, end)`. `strict`: inconsistent sizes are refused (the index
    /// containers); otherwise they are handled as FFmpeg does (a child that overruns is cut
    /// at its parent's end, a size under 8 ends the container), so that sloppy metadata
    /// containers never refuse a file FFmpeg plays, while the tables in them are still seen.
    fn children(
        &mut self,
        start: u64,
        end: u64,
        depth: u32,
        strict: bool,
        parent: Parent,
        track: &mut Track,
    ) -> Result<(), MediaError> {
        if depth > MAX_DEPTH {
            return Err(MediaError::Corrupt(format!(
                "the MP4 boxes nest deeper than {MAX_DEPTH} levels"
            )));
        }
        let mut at = start;
        // Fewer than 8 bytes left is no box: QuickTime ends some containers with a 4-byte zero
        // terminator, which FFmpeg skips the same way.
        while end.saturating_sub(at) >= 8 {
            self.boxes += 1;
            if self.boxes > MAX_BOXES {
                return Err(MediaError::Corrupt(format!(
                    "the MP4 has more than {MAX_BOXES} boxes"
                )));
            }
            let mut h = [0u8; 8];
            self.src.read_at(at, &mut h)?;
            let kind = [h[4], h[5], h[6], h[7]];
            let (size, header) = match be32(&h) {
                // Size 0: the box runs to the end of its parent (the file, at the top level).
                0 => (end - at, 8),
                1 => {
                    if end - at < 16 {
                        if !strict {
                            return Ok(());
                        }
                        return Err(MediaError::Corrupt(format!(
                            "the {} box's 64-bit size is cut off",
                            fourcc(&kind)
                        )));
                    }
                    let mut l = [0u8; 8];
                    self.src.read_at(at + 8, &mut l)?;
                    (u64::from_be_bytes(l), 16)
                }
                s => (u64::from(s), 8),
            };
            if size < header {
                if !strict {
                    return Ok(());
                }
                return Err(MediaError::Corrupt(format!(
                    "the {} box declares {size} bytes, less than its own header",
                    fourcc(&kind)
                )));
            }
            let size = if size > end - at && !strict {
                end - at
            } else {
                size
            };
            if size > end - at {
                // A recording cut off in its media data (no `moov` after it, or one before it)
                // is what FFmpeg plays as far as it goes; an index that overruns is not.
                if parent == Parent::File && !matches!(&kind, b"moov" | b"moof" | b"mfra") {
                    return Ok(());
                }
                return Err(MediaError::Corrupt(format!(
                    "the {} box ({size} bytes) runs past its {} ({} bytes left)",
                    fourcc(&kind),
                    if parent == Parent::File {
                        "file"
                    } else {
                        "parent box"
                    },
                    end - at
                )));
            }
            self.visit(kind, at + header, at + size, depth, strict, track)?;
            at += size;
        }
        Ok(())
    }

    /// One box whose payload is `[body, end)`.
    fn visit(
        &mut self,
        kind: [u8; 4],
        body: u64,
        end: u64,
        depth: u32,
        strict: bool,
        track: &mut Track,
    ) -> Result<(), MediaError> {
        let payload = end - body;
        let inner = depth + 1;
        match &kind {
            // The index: its sizes must be consistent.
            b"moov" | b"mdia" | b"minf" | b"stbl" | b"edts" | b"moof" | b"traf" | b"mfra"
            | b"mvex" => self.children(body, end, inner, strict, Parent::Other, track),
            b"trak" => {
                let mut t = Track {
                    in_trak: true,
                    ..Track::default()
                };
                self.children(body, end, inner, strict, Parent::Other, &mut t)?;
                self.finish_track(&t)
            }
            // Containers FFmpeg also walks with its generic reader, so a table hidden in them
            // is read as the track's (the last one wins): walked leniently, never refused for
            // their sizes.
            b"dinf" | b"udta" | b"tref" | b"sinf" | b"schi" | b"ilst" | b"clip" | b"matt"
            | b"rmra" | b"rmda" | b"wave" => {
                self.children(body, end, inner, false, Parent::Other, track)
            }
            b"meta" => self.meta(body, end, inner, track),
            b"stsd" => self.stsd(body, end, inner, track),
            // FFmpeg inflates a compressed header and reads the tables inside, which this
            // scan cannot see; no camera of this century writes one.
            b"cmov" => Err(MediaError::UnsupportedContainer(
                "QuickTime with a compressed header (cmov)".into(),
            )),
            b"hdlr" if payload >= 12 => {
                // version/flags, pre_defined (QuickTime: component type), handler type.
                let mut b = [0u8; 12];
                self.src.read_at(body, &mut b)?;
                let handler = [b[8], b[9], b[10], b[11]];
                // The handlers that set a track's media type in FFmpeg, where the last one
                // read wins; the others (QuickTime's data handlers in `minf`, metadata
                // handlers) leave it.
                if matches!(&handler, b"vide" | b"soun" | b"subp" | b"clcp") {
                    track.handler = handler;
                }
                Ok(())
            }
            b"stsz" => {
                // version/flags, sample_size, sample_count; then a 4-byte size per sample
                // when sample_size is 0.
                let b = self.fixed::<12>(&kind, body, payload)?;
                let (size, count) = (be32(&b[4..]), u64::from(be32(&b[8..])));
                if size == 0 {
                    self.entries("stsz", count, 4, 1, payload - 12)?;
                }
                self.declare_samples("stsz", count, track)
            }
            b"stz2" => {
                // version/flags, 3 reserved bytes and field_size, sample_count; then
                // field_size bits per sample.
                let b = self.fixed::<12>(&kind, body, payload)?;
                let bits = u64::from(b[7]);
                if !matches!(bits, 4 | 8 | 16) {
                    return Err(MediaError::Corrupt(format!(
                        "the stz2 box has a field size of {bits} bits"
                    )));
                }
                let count = u64::from(be32(&b[8..]));
                self.entries("stz2", count, bits, 8, payload - 12)?;
                self.declare_samples("stz2", count, track)
            }
            b"stts" => {
                let count = self.counted("stts", &kind, body, payload, 8)?;
                track.stts_entries = count;
                track.stts_single_delta = None;
                if count == 1 {
                    let mut e = [0u8; 8];
                    self.src.read_at(body + 8, &mut e)?;
                    track.stts_single_delta = Some(be32(&e[4..]));
                }
                Ok(())
            }
            b"ctts" => self.counted("ctts", &kind, body, payload, 8).map(drop),
            b"stss" => self.counted("stss", &kind, body, payload, 4).map(drop),
            b"stps" => self.counted("stps", &kind, body, payload, 4).map(drop),
            b"stco" => {
                track.chunks = self.counted("stco", &kind, body, payload, 4)?;
                Ok(())
            }
            b"co64" => {
                track.chunks = self.counted("co64", &kind, body, payload, 8)?;
                Ok(())
            }
            b"stsc" => {
                let count = self.counted("stsc", &kind, body, payload, 12)?;
                // Checked against the limit and the box's bytes above, so this reads at most
                // `limit` × 12 bytes.
                self.stsc_read = self.stsc_read.saturating_add(count);
                if self.stsc_read > self.limit {
                    return Err(too_many("stsc", self.stsc_read, self.limit));
                }
                track.stsc.clear();
                let mut e = [0u8; 12];
                for i in 0..count {
                    self.src.read_at(body + 8 + i * 12, &mut e)?;
                    track.stsc.push((be32(&e), be32(&e[4..])));
                }
                Ok(())
            }
            b"elst" => {
                let version = self.fixed::<8>(&kind, body, payload)?[0];
                let entry = if version == 1 { 20 } else { 12 };
                self.counted("elst", &kind, body, payload, entry).map(drop)
            }
            b"sbgp" => {
                // version/flags, grouping_type, (version 1) grouping_type_parameter, count.
                let version = self.fixed::<12>(&kind, body, payload)?[0];
                let fixed: u64 = if version == 1 { 16 } else { 12 };
                if payload < fixed {
                    return Err(MediaError::Corrupt(format!(
                        "the sbgp box is {payload} bytes, too short for its header"
                    )));
                }
                let mut c = [0u8; 4];
                self.src.read_at(body + fixed - 4, &mut c)?;
                let count = u64::from(be32(&c));
                self.entries("sbgp", count, 8, 1, payload - fixed)?;
                self.capped("sbgp", count)
            }
            b"trun" => {
                // version/flags, sample_count, then an optional data offset and first-sample
                // flags, then 4 bytes per sample for each per-sample field the flags name.
                let b = self.fixed::<8>(&kind, body, payload)?;
                let flags = be32(&b) & 0x00ff_ffff;
                let count = u64::from(be32(&b[4..]));
                let optional = 4 * (u64::from(flags & 0x1 != 0) + u64::from(flags & 0x4 != 0));
                let per_sample = 4 * u64::from((flags & 0xf00).count_ones());
                if per_sample > 0 {
                    self.entries(
                        "trun",
                        count,
                        per_sample,
                        1,
                        payload.saturating_sub(8 + optional),
                    )?;
                }
                self.add_samples("trun", count)
            }
            b"tfra" => {
                // version/flags, track_ID, 26 reserved bits and three 2-bit field lengths,
                // entry count; each entry is a time and an offset (8 bytes each in version 1)
                // and three numbers of 1-4 bytes.
                let b = self.fixed::<16>(&kind, body, payload)?;
                let lengths = be32(&b[8..]);
                let entry = if b[0] == 1 { 16 } else { 8 }
                    + u64::from((lengths >> 4) & 3)
                    + u64::from((lengths >> 2) & 3)
                    + u64::from(lengths & 3)
                    + 3;
                let count = u64::from(be32(&b[12..]));
                self.entries("tfra", count, entry, 1, payload - 16)?;
                self.capped("tfra", count)
            }
            _ => Ok(()),
        }
    }

    /// A sample table's count: the track's (the largest, if a track has several: FFmpeg reads
    /// them all), or, outside any track, straight into the file's total.
    fn declare_samples(
        &mut self,
        table: &'static str,
        count: u64,
        track: &mut Track,
    ) -> Result<(), MediaError> {
        if track.in_trak {
            track.samples = Some(track.samples.unwrap_or(0).max(count));
            Ok(())
        } else {
            self.add_samples(table, count)
        }
    }

    fn add_samples(&mut self, table: &'static str, count: u64) -> Result<(), MediaError> {
        self.samples = self.samples.saturating_add(count);
        if self.samples > self.limit {
            return Err(too_many(table, self.samples, self.limit));
        }
        Ok(())
    }

    /// `meta`: a full box in ISO files, a plain container in QuickTime ones. FFmpeg finds its
    /// first child by looking for `hdlr` word by word, and so does this.
    fn meta(
        &mut self,
        body: u64,
        end: u64,
        depth: u32,
        track: &mut Track,
    ) -> Result<(), MediaError> {
        let len = (end - body).min(MAX_SEARCHED_BYTES);
        let data = self.read_whole(body, len)?;
        let found = data
            .chunks_exact(4)
            .enumerate()
            .skip(1)
            .find(|(_, w)| *w == b"hdlr");
        match found {
            Some((word, _)) => {
                let start = body + 4 * word as u64 - 4;
                self.children(start, end, depth, false, Parent::Other, track)
            }
            None if end - body > MAX_SEARCHED_BYTES => Err(MediaError::Corrupt(format!(
                "a meta box of {} bytes without a handler in its first {MAX_SEARCHED_BYTES}",
                end - body
            ))),
            None => Ok(()),
        }
    }

    /// `stsd`: FFmpeg reads boxes after each sample entry's fixed fields (`avcC`, `esds`, ...)
    /// with its generic reader, where a sample table would be read like any other. Those fixed
    /// fields differ by media type and version, so rather than parse every entry the scan
    /// looks for the tables' names anywhere in the (small) description and checks each one
    /// that sits where a box would: after a size that fits.
    fn stsd(
        &mut self,
        body: u64,
        end: u64,
        depth: u32,
        track: &mut Track,
    ) -> Result<(), MediaError> {
        let len = end - body;
        if len > MAX_SEARCHED_BYTES {
            return Err(MediaError::Corrupt(format!(
                "a sample description of {len} bytes, more than {MAX_SEARCHED_BYTES}"
            )));
        }
        let data = self.read_whole(body, len)?;
        for i in 4..data.len().saturating_sub(4) {
            let kind = [data[i], data[i + 1], data[i + 2], data[i + 3]];
            let Some(&(_, needs)) = RAW_SCANNED.iter().find(|(k, _)| **k == kind) else {
                continue;
            };
            let at = i - 4;
            let left = (data.len() - at) as u64;
            let size = match be32(&data[at..]) {
                0 => left,
                s => u64::from(s).min(left),
            };
            if size < 8 + needs {
                continue;
            }
            let start = body + at as u64;
            self.visit(kind, start + 8, start + size, depth, false, track)?;
        }
        Ok(())
    }

    /// The first `N` bytes of a box's payload, which must have them.
    fn fixed<const N: usize>(
        &mut self,
        kind: &[u8; 4],
        body: u64,
        payload: u64,
    ) -> Result<[u8; N], MediaError> {
        if payload < N as u64 {
            return Err(MediaError::Corrupt(format!(
                "the {} box is {payload} bytes, too short for its header",
                fourcc(kind)
            )));
        }
        let mut b = [0u8; N];
        self.src.read_at(body, &mut b)?;
        Ok(b)
    }

    /// A table of version/flags, a 32-bit entry count and `entry`-byte entries: its count,
    /// checked against its bytes and the limit.
    fn counted(
        &mut self,
        table: &'static str,
        kind: &[u8; 4],
        body: u64,
        payload: u64,
        entry: u64,
    ) -> Result<u64, MediaError> {
        let b = self.fixed::<8>(kind, body, payload)?;
        let count = u64::from(be32(&b[4..]));
        self.entries(table, count, entry, 1, payload - 8)?;
        self.capped(table, count)?;
        Ok(count)
    }

    /// Refuses `count` entries of `num / den` bytes each in `bytes` bytes of table.
    fn entries(
        &self,
        table: &'static str,
        count: u64,
        num: u64,
        den: u64,
        bytes: u64,
    ) -> Result<(), MediaError> {
        let fits = bytes.saturating_mul(den) / num;
        if count > fits {
            return Err(too_many(table, count, fits));
        }
        Ok(())
    }

    fn capped(&self, table: &'static str, count: u64) -> Result<(), MediaError> {
        if count > self.limit {
            return Err(too_many(table, count, self.limit));
        }
        Ok(())
    }

    /// The checks that need the whole track: how many samples it declares, counted the way
    /// FFmpeg will index them.
    fn finish_track(&mut self, t: &Track) -> Result<(), MediaError> {
        let chunked =
            &t.handler == b"soun" && t.stts_entries == 1 && t.stts_single_delta == Some(1);
        if chunked {
            // FFmpeg indexes uncompressed audio by chunk (a few index entries per KB), so its
            // sample count is free; what the `stsc` runs imply must fit in the file.
            let mut implied: u64 = 0;
            for (i, &(first, per_chunk)) in t.stsc.iter().enumerate() {
                let next = t
                    .stsc
                    .get(i + 1)
                    .map_or(t.chunks.saturating_add(1), |n| u64::from(n.0));
                let run = next.saturating_sub(u64::from(first)).min(t.chunks);
                implied = implied.saturating_add(run.saturating_mul(u64::from(per_chunk)));
            }
            let cap = self
                .file_len
                .saturating_mul(MAX_CHUNKED_SAMPLES_PER_BYTE)
                .max(self.limit);
            if implied > cap {
                return Err(too_many("stsc", implied, cap));
            }
            return Ok(());
        }
        match t.samples {
            Some(n) => self.add_samples("stsz", n),
            None => Ok(()),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::Cursor;

    fn bx(kind: &[u8; 4], body: &[u8]) -> Vec<u8> {
        let mut v = ((body.len() + 8) as u32).to_be_bytes().to_vec();
        v.extend_from_slice(kind);
        v.extend_from_slice(body);
        v
    }

    fn full(kind: &[u8; 4], words: &[u32]) -> Vec<u8> {
        let mut body = vec![0u8; 4];
        for w in words {
            body.extend_from_slice(&w.to_be_bytes());
        }
        bx(kind, &body)
    }

    fn hdlr(kind: &[u8; 4]) -> Vec<u8> {
        let mut b = vec![0u8; 8];
        b.extend_from_slice(kind);
        b.extend_from_slice(&[0u8; 13]);
        bx(b"hdlr", &b)
    }

    /// A file of one track whose `stbl` holds `tables`, with `handler` media.
    fn file(handler: &[u8; 4], tables: &[Vec<u8>]) -> Vec<u8> {
        let stbl = bx(b"stbl", &tables.concat());
        let minf = bx(b"minf", &stbl);
        let mdia = bx(b"mdia", &[hdlr(handler), minf].concat());
        let trak = bx(b"trak", &mdia);
        let moov = bx(b"moov", &trak);
        [bx(b"ftyp", b"isom\0\0\0\0"), moov, bx(b"mdat", &[0u8; 64])].concat()
    }

    fn scan(bytes: &[u8]) -> Result<(), MediaError> {
        check_reader(
            BufReader::new(Cursor::new(bytes.to_vec())),
            bytes.len() as u64,
            &MediaLimits::default(),
        )
    }

    fn refused(bytes: &[u8]) -> (&'static str, u64, u64) {
        match scan(bytes) {
            Err(MediaError::TooManySamples {
                table,
                declared,
                limit,
            }) => (table, declared, limit),
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn the_default_limit_is_two_minutes_at_1000_per_second() {
        assert_eq!(sample_limit(&MediaLimits::default()), 120_000);
        let mut l = MediaLimits {
            max_duration_s: 0.5,
            ..MediaLimits::default()
        };
        assert_eq!(sample_limit(&l), MIN_SAMPLE_LIMIT);
        for d in [1e9, f64::INFINITY, f64::NAN, -1.0] {
            l.max_duration_s = d;
            assert_eq!(sample_limit(&l), MAX_SAMPLE_LIMIT, "{d}");
        }
    }

    #[test]
    fn honest_tables_pass() {
        let sizes: Vec<u32> = [0, 3].into_iter().chain([100; 3]).collect();
        let ok = file(
            b"vide",
            &[
                full(b"stts", &[1, 3, 512]),
                full(b"stss", &[1, 1]),
                full(b"stsc", &[1, 1, 1, 1]),
                full(b"stsz", &sizes),
                full(b"stco", &[1, 0]),
            ],
        );
        scan(&ok).unwrap();
    }

    #[test]
    fn counts_beyond_their_box_are_refused() {
        // 10 million per-sample sizes in a box that holds 2.
        let f = file(b"vide", &[full(b"stsz", &[0, 10_000_000, 7, 7])]);
        assert_eq!(refused(&f), ("stsz", 10_000_000, 2));
        for (name, entry) in [
            (b"stts", 8),
            (b"ctts", 8),
            (b"stss", 4),
            (b"stsc", 12),
            (b"stco", 4),
            (b"co64", 8),
        ] {
            let f = file(b"vide", &[full(name, &[80_000_000, 1, 2, 3])]);
            let fits = 12 / entry;
            let want = std::str::from_utf8(name).unwrap();
            assert_eq!(refused(&f), (want, 80_000_000, fits), "{want}");
        }
    }

    #[test]
    fn many_samples_of_a_constant_size_are_refused() {
        // A constant sample size needs no bytes per sample: only the limit stops it.
        let f = file(b"vide", &[full(b"stsz", &[1000, 80_000_000])]);
        assert_eq!(refused(&f), ("stsz", 80_000_000, 120_000));
        // Two tracks just under the limit each are over it together.
        let one = file(b"vide", &[full(b"stsz", &[1000, 100_000])]);
        scan(&one).unwrap();
        let trak = {
            let stbl = bx(b"stbl", &full(b"stsz", &[1000, 100_000]));
            bx(
                b"trak",
                &bx(b"mdia", &[hdlr(b"vide"), bx(b"minf", &stbl)].concat()),
            )
        };
        let two = bx(b"moov", &[trak.clone(), trak].concat());
        assert_eq!(refused(&two), ("stsz", 200_000, 120_000));
    }

    #[test]
    fn uncompressed_audio_is_judged_by_its_chunks() {
        // 10 minutes of 48 kHz PCM: 28.8M samples of 4 bytes, in 600 chunks of 48,000, is
        // indexed per chunk and passes (the file would hold its 115 MB of samples) ...
        let mut pcm = vec![
            full(b"stts", &[1, 28_800_000, 1]),
            full(b"stsz", &[4, 28_800_000]),
            full(b"stsc", &[1, 1, 48_000, 1]),
        ];
        let mut stco = vec![600];
        stco.extend(0..600);
        pcm.push(full(b"stco", &stco));
        let mut f = file(b"soun", &pcm);
        f.resize(28_800_000 / 8 + 1000, 0);
        scan(&f).unwrap();
        // ... but the same samples as video are refused, and so is a chunk that claims more
        // samples than the file could hold.
        let f = file(b"vide", &pcm);
        assert_eq!(refused(&f).0, "stsz");
        pcm[2] = full(b"stsc", &[1, 1, 4_000_000_000, 1]);
        let f = file(b"soun", &pcm);
        assert_eq!(refused(&f).0, "stsc");
    }

    #[test]
    fn fragments_count_towards_the_limit() {
        // A `trun` without per-sample fields declares its samples for free.
        let trun = full(b"trun", &[80_000_000]);
        let moof = bx(b"moof", &bx(b"traf", &trun));
        assert_eq!(refused(&moof), ("trun", 80_000_000, 120_000));
        // With a per-sample size (flag 0x200) each sample needs 4 bytes.
        let mut t = full(b"trun", &[20, 0, 0]);
        t[8..12].copy_from_slice(&0x200u32.to_be_bytes());
        let moof = bx(b"moof", &bx(b"traf", &t));
        assert_eq!(refused(&moof), ("trun", 20, 2));
        // Many small fragments add up.
        let frag = bx(b"moof", &bx(b"traf", &full(b"trun", &[50_000])));
        scan(&frag).unwrap();
        assert_eq!(refused(&frag.repeat(3)), ("trun", 150_000, 120_000));
    }

    #[test]
    fn inconsistent_sizes_are_refused() {
        let ok = file(b"vide", &[full(b"stsz", &[0, 1, 7])]);
        scan(&ok).unwrap();
        // The stsz box claims more bytes than its stbl has.
        let mut f = ok.clone();
        let at = f.windows(4).position(|w| w == b"stsz").unwrap() - 4;
        f[at..at + 4].copy_from_slice(&1000u32.to_be_bytes());
        assert!(
            matches!(scan(&f), Err(MediaError::Corrupt(ref m)) if m.contains("stsz")),
            "{:?}",
            scan(&f)
        );
        // A size under the header's.
        let mut f = ok.clone();
        f[at..at + 4].copy_from_slice(&5u32.to_be_bytes());
        assert!(matches!(scan(&f), Err(MediaError::Corrupt(_))));
        // A moov cut off by the end of the file.
        let cut = &ok[..ok.len() - 72 - 10];
        assert!(matches!(scan(cut), Err(MediaError::Corrupt(_))));
        // Media data cut off by the end of the file is a cut recording: not the scan's business.
        let mut f = ok.clone();
        let mdat = f.len() - 72;
        f[mdat..mdat + 4].copy_from_slice(&100_000u32.to_be_bytes());
        scan(&f).unwrap();
    }

    /// FFmpeg reads a sample table wherever its generic reader meets one (the last one read
    /// wins), so hiding one outside `stbl` must not get it past the scan.
    #[test]
    fn tables_hidden_outside_the_sample_table_box_are_checked() {
        let hostile = full(b"stsz", &[1000, 80_000_000]);
        let honest_stbl = bx(b"stbl", &full(b"stsz", &[0, 1, 7]));
        let mdia = bx(
            b"mdia",
            &[hdlr(b"vide"), bx(b"minf", &honest_stbl)].concat(),
        );
        // In the track's user data, after an honest table.
        let trak = bx(b"trak", &[mdia.clone(), bx(b"udta", &hostile)].concat());
        assert_eq!(refused(&bx(b"moov", &trak)), ("stsz", 80_000_000, 120_000));
        // In `moov`, outside any track (counted with the honest track's one sample).
        let moov = bx(b"moov", &[bx(b"trak", &mdia), hostile.clone()].concat());
        assert_eq!(refused(&moov), ("stsz", 80_000_001, 120_000));
        // Among a sample entry's extension boxes (after `avc1`'s 78 bytes of fixed fields).
        let mut entry = vec![0u8; 78];
        entry.extend(bx(b"avcC", &[1, 2, 3]));
        entry.extend(&hostile);
        let stsd = bx(
            b"stsd",
            &[vec![0, 0, 0, 0, 0, 0, 0, 1], bx(b"avc1", &entry)].concat(),
        );
        let f = file(b"vide", &[stsd, full(b"stsz", &[0, 1, 7])]);
        assert_eq!(refused(&f), ("stsz", 80_000_000, 120_000));
        // In a QuickTime `meta` (no version field: the scan finds its `hdlr` as FFmpeg does).
        let meta = bx(b"meta", &[hdlr(b"mdta"), hostile.clone()].concat());
        let moov = bx(b"moov", &bx(b"udta", &meta));
        assert_eq!(refused(&moov), ("stsz", 80_000_000, 120_000));
        // A compressed header would hide everything.
        let cmov = bx(b"moov", &bx(b"cmov", &[0u8; 32]));
        assert!(matches!(
            scan(&cmov),
            Err(MediaError::UnsupportedContainer(_))
        ));
    }

    /// A `soun` track with one `stts` entry of duration 1 is indexed by chunk, but FFmpeg
    /// takes the track's last media handler: a `vide` one read later makes it video again.
    #[test]
    fn a_second_handler_cannot_pass_video_off_as_uncompressed_audio() {
        let tables = [
            full(b"stts", &[1, 80_000_000, 1]),
            full(b"stsz", &[4, 80_000_000]),
            full(b"stsc", &[1, 1, 1, 1]),
            full(b"stco", &[1, 0]),
        ]
        .concat();
        scan(&file(b"soun", std::slice::from_ref(&tables))).unwrap();
        let minf = bx(b"minf", &[hdlr(b"vide"), bx(b"stbl", &tables)].concat());
        let trak = bx(b"trak", &bx(b"mdia", &[hdlr(b"soun"), minf].concat()));
        assert_eq!(refused(&bx(b"moov", &trak)), ("stsz", 80_000_000, 120_000));
        // QuickTime's data handler in `minf` names no media type and changes nothing.
        let minf = bx(b"minf", &[hdlr(b"alis"), bx(b"stbl", &tables)].concat());
        let trak = bx(b"trak", &bx(b"mdia", &[hdlr(b"soun"), minf].concat()));
        scan(&bx(b"moov", &trak)).unwrap();
    }

    /// Metadata containers are read as FFmpeg reads them: an overrunning child is cut at the
    /// end of its parent, a size under 8 ends the container, and neither refuses the file.
    #[test]
    fn sloppy_metadata_sizes_do_not_refuse_a_file() {
        let mut title = bx(b"\xa9nam", b"a title");
        title[0..4].copy_from_slice(&4000u32.to_be_bytes());
        let udta = bx(b"udta", &[bx(b"free", &[]), title].concat());
        let f = file(b"vide", &[full(b"stsz", &[0, 1, 7])]);
        let at = f.windows(4).position(|w| w == b"moov").unwrap() - 4;
        let moov_len = u32::from_be_bytes(f[at..at + 4].try_into().unwrap()) as usize;
        let mut moov = f[at..at + moov_len].to_vec();
        moov.extend(&udta);
        let total = moov.len() as u32;
        moov[0..4].copy_from_slice(&total.to_be_bytes());
        scan(&moov).unwrap();
        let mut short = bx(b"udta", &[0, 0, 0, 5, b'x', b'x', b'x', b'x']);
        short.extend(full(b"stsz", &[0, 0]));
        scan(&bx(b"moov", &short)).unwrap();
    }

    #[test]
    fn the_scan_itself_is_bounded() {
        let free = bx(b"free", &[]);
        let many = free.repeat(MAX_BOXES as usize + 1);
        assert!(matches!(scan(&many), Err(MediaError::Corrupt(ref m)) if m.contains("boxes")));
        let mut deep = full(b"stsz", &[0, 0]);
        for _ in 0..=MAX_DEPTH {
            deep = bx(b"moov", &deep);
        }
        assert!(matches!(scan(&deep), Err(MediaError::Corrupt(ref m)) if m.contains("deeper")));
        // The stsc runs it reads add up against the sample limit, however many boxes hold them.
        let mut runs = vec![12_000];
        runs.extend(std::iter::repeat_n(1, 3 * 12_000));
        let stsc = full(b"stsc", &runs);
        let f = file(b"soun", &vec![stsc; 11]);
        assert_eq!(refused(&f), ("stsc", 132_000, 120_000));
        // Sample descriptions are read whole, so a huge one is refused.
        let stsd = bx(b"stsd", &vec![0u8; MAX_SEARCHED_BYTES as usize + 1]);
        assert!(
            matches!(scan(&file(b"vide", &[stsd])), Err(MediaError::Corrupt(ref m)) if m.contains("sample description"))
        );
    }
}
