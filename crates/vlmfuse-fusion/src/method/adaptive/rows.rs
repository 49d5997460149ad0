//! The pool's per-entry rows: everything a neighbour's weighted sums read of it, together in
//! one block of whole cache lines.
//!
//! Why: at scale the weighted sums of an E-step (docs/METHOD.md §2) visit `K` neighbours
//! scattered over a pool of a hundred thousand entries or more, and wait on memory. With the
//! soft truths, the flags, the presence and the reports in five arrays, a neighbour cost about
//! seven cache lines; in one 64-byte-aligned block it costs `⌈(8L + 2 + n + nL) / 64⌉`, three
//! for fourteen labels and three reporters. The values are the same ones, so every sum keeps
//! its bits. (Reports packed as bits make that two lines; measured, no faster, so the plainer
//! bytes stay.)
//!
//! A row holds, in order: `L` soft truths (f64), the labelled and partial flags, `n` presence
//! flags, and `n L` reports (0 where the reporter was absent), as the bank holds them. The
//! reports and presence are copies of the bank's (which the whole-pool sums and the snapshots'
//! other readers use); they never change once an entry has joined.

use serde::{Deserialize, Serialize};

/// One cache line; the rows are whole lines, so each starts on a line.
#[derive(Clone, Copy, Debug, Default, bytemuck::Pod, bytemuck::Zeroable)]
#[repr(C, align(64))]
struct Line([u64; 8]);

const LINE: usize = std::mem::size_of::<Line>();

/// The rows of every pool entry, in pool order.
#[derive(Debug, Clone, Default)]
pub struct Rows {
    n: usize,
    l: usize,
    /// Lines per entry.
    stride: usize,
    lines: Vec<Line>,
}

impl Rows {
    pub fn new(n: usize, l: usize) -> Self {
        let bytes = 8 * l + 2 + n + n * l;
        Self {
            n,
            l,
            stride: bytes.div_ceil(LINE),
            lines: Vec::new(),
        }
    }

    pub fn len(&self) -> usize {
        self.lines.len() / self.stride
    }

    fn flags_at(&self) -> usize {
        8 * self.l
    }

    fn present_at(&self) -> usize {
        8 * self.l + 2
    }

    fn reports_at(&self) -> usize {
        8 * self.l + 2 + self.n
    }

    #[inline]
    fn row(&self, pos: usize) -> &[Line] {
        &self.lines[pos * self.stride..(pos + 1) * self.stride]
    }

    #[inline]
    fn row_mut(&mut self, pos: usize) -> &mut [Line] {
        &mut self.lines[pos * self.stride..(pos + 1) * self.stride]
    }

    #[inline]
    fn bytes(&self, pos: usize) -> &[u8] {
        bytemuck::cast_slice(self.row(pos))
    }

    /// Appends an entry; `reports` are read only where `present` says so (0 elsewhere).
    pub fn push(
        &mut self,
        soft: &[f64],
        labelled: bool,
        partial: bool,
        present: &[bool],
        reports: &[u8],
    ) {
        debug_assert_eq!((soft.len(), present.len()), (self.l, self.n));
        let (l, n) = (self.l, self.n);
        let (fa, pa, ra) = (self.flags_at(), self.present_at(), self.reports_at());
        let mut row = vec![Line::default(); self.stride];
        let b: &mut [u8] = bytemuck::cast_slice_mut(&mut row);
        for (k, &t) in soft.iter().enumerate() {
            b[8 * k..8 * k + 8].copy_from_slice(&t.to_ne_bytes());
        }
        b[fa] = labelled as u8;
        b[fa + 1] = partial as u8;
        for (i, &p) in present.iter().enumerate().take(n) {
            b[pa + i] = p as u8;
            for k in 0..l {
                b[ra + i * l + k] = if p { reports[i * l + k] } else { 0 };
            }
        }
        self.lines.extend_from_slice(&row);
    }

    #[inline]
    pub fn soft(&self, pos: usize) -> &[f64] {
        &bytemuck::cast_slice::<Line, f64>(self.row(pos))[..self.l]
    }

    #[inline]
    pub fn soft_mut(&mut self, pos: usize) -> &mut [f64] {
        let l = self.l;
        &mut bytemuck::cast_slice_mut::<Line, f64>(self.row_mut(pos))[..l]
    }

    #[inline]
    pub fn labelled(&self, pos: usize) -> bool {
        self.bytes(pos)[self.flags_at()] != 0
    }

    #[inline]
    pub fn partial(&self, pos: usize) -> bool {
        self.bytes(pos)[self.flags_at() + 1] != 0
    }

    pub fn set_labelled(&mut self, pos: usize, on: bool) {
        let at = self.flags_at();
        bytemuck::cast_slice_mut::<Line, u8>(self.row_mut(pos))[at] = on as u8;
    }

    pub fn set_partial(&mut self, pos: usize, on: bool) {
        let at = self.flags_at() + 1;
        bytemuck::cast_slice_mut::<Line, u8>(self.row_mut(pos))[at] = on as u8;
    }

    /// The entry's `n` presence flags (0/1).
    #[inline]
    pub fn present(&self, pos: usize) -> &[u8] {
        let at = self.present_at();
        &self.bytes(pos)[at..at + self.n]
    }

    /// The entry's `n L` reports, reporter by reporter (0 where the reporter was absent).
    #[inline]
    pub fn reports(&self, pos: usize) -> &[u8] {
        let at = self.reports_at();
        &self.bytes(pos)[at..at + self.n * self.l]
    }

    /// Keeps the entries with `keep[pos]` true, in order.
    pub fn retain(&mut self, keep: &[bool]) {
        debug_assert_eq!(keep.len(), self.len());
        let s = self.stride;
        let mut w = 0;
        for (r, &k) in keep.iter().enumerate() {
            if k {
                if w != r {
                    self.lines.copy_within(r * s..(r + 1) * s, w * s);
                }
                w += 1;
            }
        }
        self.lines.truncate(w * s);
    }

    /// Asks the processor to start loading the entry's row. A hint only.
    #[inline]
    pub fn prefetch(&self, pos: usize) {
        #[cfg(target_arch = "x86_64")]
        {
            use std::arch::x86_64::{_mm_prefetch, _MM_HINT_T0};
            let s = self.stride;
            if let Some(row) = self.lines.get(pos * s..(pos + 1) * s) {
                for line in row {
                    // SAFETY: a prefetch is a hint; the pointer is to a live line.
                    unsafe { _mm_prefetch(line as *const Line as *const i8, _MM_HINT_T0) };
                }
            }
        }
        #[cfg(not(target_arch = "x86_64"))]
        let _ = pos;
    }
}

/// Serialised as `(n, L, bytes)`: the lines as they are in memory, so a snapshot writes and
/// reads them in one copy. The soft truths are in the machine's byte order (little-endian on
/// every platform the project builds for, as postcard's own f64s).
impl Serialize for Rows {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        (
            self.n,
            self.l,
            serde_bytes::Bytes::new(bytemuck::cast_slice(&self.lines)),
        )
            .serialize(s)
    }
}

impl<'de> Deserialize<'de> for Rows {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        let (n, l, bytes): (usize, usize, serde_bytes::ByteBuf) = Deserialize::deserialize(d)?;
        let mut rows = Rows::new(n, l);
        if bytes.len() % (rows.stride * LINE) != 0 {
            return Err(serde::de::Error::custom(format!(
                "pool rows: {} bytes is not a whole number of {}-byte rows",
                bytes.len(),
                rows.stride * LINE
            )));
        }
        rows.lines = vec![Line::default(); bytes.len() / LINE];
        bytemuck::cast_slice_mut::<Line, u8>(&mut rows.lines).copy_from_slice(&bytes);
        Ok(rows)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rows_keep_what_they_are_given_through_retain_and_serde() {
        for (n, l) in [(3, 14), (1, 1), (8, 20), (2, 7)] {
            let mut rows = Rows::new(n, l);
            let mut want = Vec::new();
            for e in 0..9usize {
                let soft: Vec<f64> = (0..l).map(|k| (e * 31 + k) as f64 / 7.0).collect();
                let present: Vec<bool> = (0..n).map(|i| (e + i) % 3 != 0).collect();
                let reports: Vec<u8> = (0..n * l).map(|j| ((e * j + j) % 3) as u8).collect();
                rows.push(&soft, e % 4 == 0, e % 5 == 1, &present, &reports);
                let masked: Vec<u8> = (0..n * l)
                    .map(|j| if present[j / l] { reports[j] } else { 0 })
                    .collect();
                let p: Vec<u8> = present.iter().map(|&p| p as u8).collect();
                want.push((soft, e % 4 == 0, e % 5 == 1, p, masked));
            }
            rows.soft_mut(2)[l - 1] = -0.25;
            want[2].0[l - 1] = -0.25;
            rows.set_labelled(3, true);
            want[3].1 = true;
            rows.set_partial(3, false);
            want[3].2 = false;
            let keep: Vec<bool> = (0..9).map(|e| e % 3 != 1).collect();
            rows.retain(&keep);
            let want: Vec<_> = want
                .into_iter()
                .zip(&keep)
                .filter(|(_, &k)| k)
                .map(|(w, _)| w)
                .collect();
            let json = serde_json::to_string(&rows).unwrap();
            let back: Rows = serde_json::from_str(&json).unwrap();
            for r in [&rows, &back] {
                assert_eq!(r.len(), want.len());
                for (pos, w) in want.iter().enumerate() {
                    assert_eq!(r.soft(pos), &w.0[..]);
                    assert_eq!((r.labelled(pos), r.partial(pos)), (w.1, w.2));
                    assert_eq!(r.present(pos), &w.3[..]);
                    assert_eq!(r.reports(pos), &w.4[..]);
                    let at = r.row(pos).as_ptr() as usize;
                    assert_eq!(at % 64, 0, "row {pos} starts off a cache line");
                }
            }
        }
        let bad = serde_json::to_string(&(3usize, 14usize, vec![0u8; 100])).unwrap();
        assert!(serde_json::from_str::<Rows>(&bad).is_err());
    }
}
