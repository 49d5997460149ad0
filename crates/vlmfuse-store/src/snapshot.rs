//! Snapshots of the engine, so that a restart replays only the events after the latest one.
//!
//! The events stay the truth: a snapshot is a cache of "the engine after the first `rounds`
//! rounds and the first `labelled` feedbacks", and [`crate::Store::load_engine`] uses one only
//! when everything about it checks out (checksum, format, engine layout, method, the setup the
//! engine was built with, and two anchors into the database's history). Anything else is
//! ignored with a warning and the full replay runs, so a snapshot can make a restart faster but
//! never change its result: the engine is serialised field by field with every `f64` by its
//! bits, and the tail replay makes the very operations the live service made.
//!
//! A file is `MAGIC | u32 header length | header (JSON) | engine (postcard) | u32 CRC-32` of
//! everything before the CRC, written to a temporary name, synced, renamed into place and the
//! directory synced, so a crash mid-write leaves the previous snapshot in force. postcard
//! because it is serde's compact binary form (floats as their little-endian bits, no schema to
//! keep beside the code) and reads straight from the memory-mapped file; CRC-32 (crc32fast)
//! because it catches torn and flipped bytes at memory speed, and the snapshot is not a trust
//! boundary: whoever can write the data directory can write the database too.

use crate::StoreError;
use serde::{Deserialize, Serialize};
use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};
use vlmfuse_fusion::{Engine, ENGINE_LAYOUT};

/// The directory under the data directory that holds the snapshots.
pub const SNAPSHOT_DIR: &str = "snapshots";

/// Version of the file layout (magic, header, trailer); the engine's own is [`ENGINE_LAYOUT`].
pub const SNAPSHOT_FORMAT: u32 = 1;

const MAGIC: &[u8; 8] = b"VLMFSNAP";

/// A point in the database's history, and what identifies it there.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Anchor {
    /// Rounds with `seq` below this are in the engine (the next `seq` at the time).
    pub rounds: u64,
    /// Feedbacks with `labelled_order` below this are in the engine.
    pub labelled: u64,
    /// `(seq, created_ms)` of the last round in it: a snapshot of another database, or of one
    /// whose history was rewritten, does not match.
    pub last_round: Option<(u64, i64)>,
    /// `(seq, created_ms)` of the last feedback in it.
    pub last_feedback: Option<(u64, i64)>,
}

/// What a snapshot file says of itself.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Header {
    pub format: u32,
    pub engine_layout: u32,
    /// The crate version that wrote it (a snapshot is read only by the version that wrote it).
    pub version: String,
    pub method: String,
    pub anchor: Anchor,
    pub created_ms: i64,
}

/// A snapshot written: where, and how big.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Written {
    pub path: PathBuf,
    pub bytes: u64,
}

/// What a restart took from a snapshot.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Used {
    pub path: PathBuf,
    pub anchor: Anchor,
    /// Rounds and feedbacks replayed after it.
    pub tail_rounds: u64,
    pub tail_feedback: u64,
}

/// The snapshot directory of a data directory.
pub fn dir_of(data_dir: &Path) -> PathBuf {
    data_dir.join(SNAPSHOT_DIR)
}

fn file_name(a: &Anchor) -> String {
    format!("snapshot-{:012}-{:012}.bin", a.labelled, a.rounds)
}

/// `(labelled, rounds)` of a snapshot's file name; `None` for anything else in the directory.
fn parse_name(name: &str) -> Option<(u64, u64)> {
    let rest = name.strip_prefix("snapshot-")?.strip_suffix(".bin")?;
    let (l, r) = rest.split_once('-')?;
    Some((l.parse().ok()?, r.parse().ok()?))
}

/// The snapshots under `dir`, newest (most events) first.
pub fn list(dir: &Path) -> Vec<PathBuf> {
    let Ok(rd) = std::fs::read_dir(dir) else {
        return Vec::new();
    };
    let mut found: Vec<((u64, u64), PathBuf)> = rd
        .filter_map(|e| e.ok())
        .filter_map(|e| {
            let name = e.file_name().into_string().ok()?;
            Some((parse_name(&name)?, e.path()))
        })
        .collect();
    found.sort_by_key(|f| std::cmp::Reverse(f.0));
    found.into_iter().map(|(_, p)| p).collect()
}

/// A writer that keeps the CRC of what went through it.
struct Crc<W> {
    inner: W,
    crc: crc32fast::Hasher,
    bytes: u64,
}

impl<W: Write> Write for Crc<W> {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        let n = self.inner.write(buf)?;
        self.crc.update(&buf[..n]);
        self.bytes += n as u64;
        Ok(n)
    }
    fn flush(&mut self) -> std::io::Result<()> {
        self.inner.flush()
    }
}

fn io_err(path: &Path, what: &str, e: impl std::fmt::Display) -> StoreError {
    StoreError::Snapshot(format!("{what} {}: {e}", path.display()))
}

/// Writes a snapshot of `engine`, which must be the engine after exactly the events `anchor`
/// names, under `dir` (created if needed), then removes all but the newest `keep` (at least 1).
/// Safe to call from any thread with a clone of the live engine: it touches no database.
pub fn write(
    dir: &Path,
    engine: &Engine,
    anchor: &Anchor,
    keep: usize,
) -> Result<Written, StoreError> {
    if engine.labelled() != anchor.labelled {
        return Err(StoreError::Snapshot(format!(
            "the engine has {} labelled rounds but the anchor says {}",
            engine.labelled(),
            anchor.labelled
        )));
    }
    std::fs::create_dir_all(dir).map_err(|e| io_err(dir, "cannot create", e))?;
    let path = dir.join(file_name(anchor));
    let tmp = dir.join(format!(".tmp-{}-{}", std::process::id(), file_name(anchor)));
    let header = Header {
        format: SNAPSHOT_FORMAT,
        engine_layout: ENGINE_LAYOUT,
        version: env!("CARGO_PKG_VERSION").to_string(),
        method: engine.method().name().to_string(),
        anchor: anchor.clone(),
        created_ms: crate::timestamp_ms(),
    };
    let res = (|| -> Result<u64, StoreError> {
        let file = File::create(&tmp).map_err(|e| io_err(&tmp, "cannot create", e))?;
        let mut w = Crc {
            inner: BufWriter::with_capacity(1 << 20, file),
            crc: crc32fast::Hasher::new(),
            bytes: 0,
        };
        let head = serde_json::to_vec(&header)?;
        let werr = |e: std::io::Error| io_err(&tmp, "cannot write", e);
        w.write_all(MAGIC).map_err(werr)?;
        w.write_all(&(head.len() as u32).to_le_bytes())
            .map_err(werr)?;
        w.write_all(&head).map_err(werr)?;
        postcard::to_io(engine, &mut w).map_err(|e| io_err(&tmp, "cannot serialise into", e))?;
        let crc = w.crc.clone().finalize();
        let bytes = w.bytes + 4;
        let mut inner = w.inner;
        inner.write_all(&crc.to_le_bytes()).map_err(werr)?;
        let file = inner
            .into_inner()
            .map_err(|e| io_err(&tmp, "cannot write", e.error()))?;
        file.sync_all()
            .map_err(|e| io_err(&tmp, "cannot sync", e))?;
        Ok(bytes)
    })();
    let bytes = match res {
        Ok(b) => b,
        Err(e) => {
            let _ = std::fs::remove_file(&tmp);
            return Err(e);
        }
    };
    std::fs::rename(&tmp, &path).map_err(|e| io_err(&path, "cannot rename into", e))?;
    File::open(dir)
        .and_then(|d| d.sync_all())
        .map_err(|e| io_err(dir, "cannot sync", e))?;
    for old in list(dir).into_iter().skip(keep.max(1)) {
        if let Err(e) = std::fs::remove_file(&old) {
            tracing::warn!(path = %old.display(), "cannot remove an old snapshot: {e}");
        }
    }
    Ok(Written { path, bytes })
}

/// Removes temporary files a crash left mid-write (any process's: the directory's lock says
/// no other writer is running).
pub fn remove_leftovers(dir: &Path) {
    let Ok(rd) = std::fs::read_dir(dir) else {
        return;
    };
    for e in rd.filter_map(|e| e.ok()) {
        if e.file_name().to_string_lossy().starts_with(".tmp-") {
            let _ = std::fs::remove_file(e.path());
        }
    }
}

/// A snapshot file whose checksum, format and version checked out, its engine not yet decoded:
/// the checks on its header come first, so that a snapshot of another method or history is
/// refused without decoding an engine of possibly gigabytes.
pub struct Opened {
    map: memmap2::Mmap,
    /// Where the engine's bytes start.
    at: usize,
    pub header: Header,
}

/// Opens a snapshot: its header, or why it cannot be used (before any check that needs the
/// database or the engine: those are the caller's).
pub fn open(path: &Path) -> Result<Opened, String> {
    let file = File::open(path).map_err(|e| format!("cannot open: {e}"))?;
    // SAFETY: the file is opened read-only and only this process writes the snapshot directory
    // (it holds the data directory's lock); snapshots are never modified in place, only
    // created under a temporary name and renamed, so the mapped bytes do not change under us.
    let map = unsafe { memmap2::Mmap::map(&file) }.map_err(|e| format!("cannot map: {e}"))?;
    let b: &[u8] = &map;
    if b.len() < MAGIC.len() + 8 || &b[..MAGIC.len()] != MAGIC {
        return Err("not a vlmfuse snapshot (bad magic or too short)".into());
    }
    let (body, trailer) = b.split_at(b.len() - 4);
    let want = u32::from_le_bytes(trailer.try_into().expect("4 bytes"));
    let got = crc32fast::hash(body);
    if want != got {
        return Err(format!(
            "checksum mismatch (stored {want:08x}, computed {got:08x}): the file is damaged"
        ));
    }
    let at = MAGIC.len();
    let hlen = u32::from_le_bytes(body[at..at + 4].try_into().expect("4 bytes")) as usize;
    let head = body
        .get(at + 4..at + 4 + hlen)
        .ok_or("the header runs past the end of the file")?;
    let header: Header =
        serde_json::from_slice(head).map_err(|e| format!("unreadable header: {e}"))?;
    if header.format != SNAPSHOT_FORMAT {
        return Err(format!(
            "file format {}, this build reads {SNAPSHOT_FORMAT}",
            header.format
        ));
    }
    if header.engine_layout != ENGINE_LAYOUT || header.version != env!("CARGO_PKG_VERSION") {
        return Err(format!(
            "written by vlmfuse {} (engine layout {}), this is {} (layout {ENGINE_LAYOUT})",
            header.version,
            header.engine_layout,
            env!("CARGO_PKG_VERSION")
        ));
    }
    Ok(Opened {
        map,
        at: at + 4 + hlen,
        header,
    })
}

impl Opened {
    /// Decodes the engine.
    pub fn engine(&self) -> Result<Engine, String> {
        let body = &self.map[..self.map.len() - 4];
        let (engine, rest): (Engine, &[u8]) = postcard::take_from_bytes(&body[self.at..])
            .map_err(|e| format!("unreadable engine: {e}"))?;
        if !rest.is_empty() {
            return Err(format!("{} bytes after the engine", rest.len()));
        }
        if engine.labelled() != self.header.anchor.labelled {
            return Err("the engine's labelled count differs from its header".into());
        }
        Ok(engine)
    }
}

/// Reads a snapshot whole: its header and engine ([`open`], then [`Opened::engine`]).
pub fn read(path: &Path) -> Result<(Header, Engine), String> {
    let o = open(path)?;
    let engine = o.engine()?;
    Ok((o.header, engine))
}
