//! Approximate nearest neighbours for large pools (docs/METHOD.md §6): an inverted file over
//! spherical k-means cells, on an 8-bit copy of every context. A query is compared with the
//! cell centres, the entries of its `probe` nearest cells are ranked by their 8-bit cosine,
//! and the best `ef` of them are the candidates the pool scores exactly and ranks with its
//! usual rule.
//!
//! Why not a graph index from a crate (docs/METHOD.md §6 has the measurements): the engine is
//! a pure function of its events, and a snapshot plus the tail must rebuild the very engine a
//! full replay builds. `usearch` and `hnsw_rs` keep the random generator that picks each new
//! node's level outside what they save (per-thread contexts reseeded on load, a fresh seeded
//! generator on reload), so an index read back from a snapshot places later rounds on other
//! levels than the index that never stopped, and the two engines drift apart; `hnsw` (rust-cv)
//! saves its generator but panics on a search that finds fewer than the requested neighbours.
//! An inverted file has no hidden state: the cells are fixed when the pool first reaches
//! `ann_min` (k-means from a fixed initialisation on an evenly spaced sample), a new round
//! joins its nearest cell, and an evicted one simply leaves its cell's list; all of it is
//! plain data, saved and restored field by field, and every number in it is computed in one
//! fixed order (integer dot products for the codes), so replays stay exact.

use crate::bank::scan_f32;

/// Lloyd iterations of the k-means that fixes the cells.
const KMEANS_ITERS: usize = 6;
/// Sample points per cell for the k-means (evenly spaced over the pool).
const SAMPLE_PER_CELL: usize = 16;

/// 8-bit copy of a context: `code[i] ≈ x[i] / scale`, a quarter of the f32 copy.
pub fn quantise(x: &[f32], out: &mut Vec<i8>) -> f32 {
    let max = x.iter().fold(0.0f32, |m, v| m.max(v.abs()));
    let scale = if max > 0.0 { max / 127.0 } else { 1.0 };
    out.extend(
        x.iter()
            .map(|v| (v / scale).round().clamp(-127.0, 127.0) as i8),
    );
    scale
}

#[inline(always)]
fn dot_i8_body(a: &[i8], b: &[i8]) -> i32 {
    let mut acc = [0i32; 32];
    let ca = a.chunks_exact(32);
    let cb = b.chunks_exact(32);
    let (ra, rb) = (ca.remainder(), cb.remainder());
    for (x, y) in ca.zip(cb) {
        for l in 0..32 {
            acc[l] += x[l] as i32 * y[l] as i32;
        }
    }
    let mut s: i32 = acc.iter().sum();
    for (x, y) in ra.iter().zip(rb) {
        s += *x as i32 * *y as i32;
    }
    s
}

/// AVX2: sixteen codes widened to i16 per step, multiplied and summed in pairs into eight i32
/// lanes (`vpmaddwd`). Integer arithmetic, so the sum is the portable loop's exactly.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn dot_i8_avx2(a: &[i8], b: &[i8]) -> i32 {
    use std::arch::x86_64::*;
    let n = a.len().min(b.len());
    let mut acc = _mm256_setzero_si256();
    let mut i = 0;
    while i + 16 <= n {
        // SAFETY: i + 16 <= n bounds both 16-byte (unaligned) loads.
        let (va, vb) = unsafe {
            (
                _mm256_cvtepi8_epi16(_mm_loadu_si128(a.as_ptr().add(i) as *const __m128i)),
                _mm256_cvtepi8_epi16(_mm_loadu_si128(b.as_ptr().add(i) as *const __m128i)),
            )
        };
        acc = _mm256_add_epi32(acc, _mm256_madd_epi16(va, vb));
        i += 16;
    }
    let mut lanes = [0i32; 8];
    // SAFETY: `lanes` is 32 bytes.
    unsafe { _mm256_storeu_si256(lanes.as_mut_ptr() as *mut __m256i, acc) };
    let mut s: i32 = lanes.iter().sum();
    for j in i..n {
        s += a[j] as i32 * b[j] as i32;
    }
    s
}

/// AVX-512 VNNI: 64 codes per step. `vpdpbusd` multiplies unsigned bytes by signed ones, so
/// the query's codes are shifted into unsigned range (`a + 128`, an exclusive or with 0x80)
/// and `128 · Σb` (a second `vpdpbusd` against ones) is taken off again: integer arithmetic
/// throughout, so the sum is the portable loop's exactly, a quarter of AVX2's instructions.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512bw,avx512vnni")]
unsafe fn dot_i8_vnni(a: &[i8], b: &[i8]) -> i32 {
    use std::arch::x86_64::*;
    let n = a.len().min(b.len());
    let flip = _mm512_set1_epi8(-128);
    let ones = _mm512_set1_epi8(1);
    let (mut ab, mut sb) = (_mm512_setzero_si512(), _mm512_setzero_si512());
    let mut i = 0;
    while i < n {
        // The last step loads only the bytes left (the others read as zero, and a zero `b`
        // byte adds nothing to either sum).
        let mask: __mmask64 = if n - i >= 64 {
            !0
        } else {
            (1u64 << (n - i)) - 1
        };
        // SAFETY: the mask keeps both loads inside `a[i..n]` and `b[i..n]`.
        let (va, vb) = unsafe {
            (
                _mm512_maskz_loadu_epi8(mask, a.as_ptr().add(i)),
                _mm512_maskz_loadu_epi8(mask, b.as_ptr().add(i)),
            )
        };
        ab = _mm512_dpbusd_epi32(ab, _mm512_xor_si512(va, flip), vb);
        sb = _mm512_dpbusd_epi32(sb, ones, vb);
        i += 64;
    }
    _mm512_reduce_add_epi32(ab) - 128 * _mm512_reduce_add_epi32(sb)
}

/// Which integer dot product this processor runs, decided once.
#[derive(Clone, Copy)]
enum DotKind {
    Portable,
    #[cfg(target_arch = "x86_64")]
    Avx2,
    #[cfg(target_arch = "x86_64")]
    Vnni,
}

fn dot_kind() -> DotKind {
    #[cfg(target_arch = "x86_64")]
    {
        use std::sync::OnceLock;
        static KIND: OnceLock<DotKind> = OnceLock::new();
        *KIND.get_or_init(|| {
            if std::arch::is_x86_feature_detected!("avx512f")
                && std::arch::is_x86_feature_detected!("avx512bw")
                && std::arch::is_x86_feature_detected!("avx512vnni")
            {
                DotKind::Vnni
            } else if std::arch::is_x86_feature_detected!("avx2") {
                DotKind::Avx2
            } else {
                DotKind::Portable
            }
        })
    }
    #[cfg(not(target_arch = "x86_64"))]
    DotKind::Portable
}

/// Integer dot product of two codes with the kind [`dot_kind`] picked (exact, so the same on
/// every processor).
#[inline(always)]
fn dot_i8_with(kind: DotKind, a: &[i8], b: &[i8]) -> i32 {
    match kind {
        DotKind::Portable => dot_i8_body(a, b),
        // SAFETY: `dot_kind` picked each of these only after detecting its features.
        #[cfg(target_arch = "x86_64")]
        DotKind::Avx2 => unsafe { dot_i8_avx2(a, b) },
        #[cfg(target_arch = "x86_64")]
        DotKind::Vnni => unsafe { dot_i8_vnni(a, b) },
    }
}

/// One cell's entries: pool positions (ascending), and their scales and codes stored
/// contiguously, so that a query reads a cell as one stream instead of one random access per
/// entry.
#[derive(Debug, Clone, Default, serde::Serialize, serde::Deserialize)]
struct Cell {
    pos: Vec<u32>,
    scales: Vec<f32>,
    codes: Vec<i8>,
}

/// The index: cell centres and the cells' entries.
#[derive(Debug, Clone, Default, serde::Serialize, serde::Deserialize)]
pub struct Ivf {
    dim: usize,
    /// `cells * dim` unit-norm centres.
    centres: Vec<f32>,
    lists: Vec<Cell>,
    len: usize,
}

/// The index of the largest value, the first of equal ones.
fn argmax(v: &[f32]) -> usize {
    let mut best = 0;
    for (i, &x) in v.iter().enumerate() {
        if x > v[best] {
            best = i;
        }
    }
    best
}

impl Ivf {
    /// Fixes `cells` cells by spherical k-means over an evenly spaced sample of the `rows`
    /// (f32 contexts, `dim` each, unit norm), started from evenly spaced rows, and files every
    /// row in its nearest cell.
    pub fn train(rows: &[f32], dim: usize, cells: usize) -> Self {
        let n = rows.len() / dim.max(1);
        let cells = cells.clamp(1, n.max(1));
        let row = |i: usize| &rows[i * dim..(i + 1) * dim];
        let take = (cells * SAMPLE_PER_CELL).min(n);
        let sample: Vec<usize> = (0..take).map(|i| i * n / take).collect();
        let mut centres: Vec<f32> = Vec::with_capacity(cells * dim);
        for c in 0..cells {
            centres.extend_from_slice(row(sample[c * take / cells]));
        }
        let mut sims = Vec::with_capacity(cells);
        for _ in 0..KMEANS_ITERS {
            let mut sums = vec![0.0f64; cells * dim];
            let mut counts = vec![0usize; cells];
            for &i in &sample {
                scan_f32(&centres, row(i), dim, &mut sims);
                let c = argmax(&sims);
                counts[c] += 1;
                for (s, &v) in sums[c * dim..(c + 1) * dim].iter_mut().zip(row(i)) {
                    *s += v as f64;
                }
            }
            for c in 0..cells {
                let s = &sums[c * dim..(c + 1) * dim];
                let norm = s.iter().map(|v| v * v).sum::<f64>().sqrt();
                // An empty cell keeps its centre.
                if counts[c] > 0 && norm > 0.0 {
                    for (d, &v) in centres[c * dim..(c + 1) * dim].iter_mut().zip(s) {
                        *d = (v / norm) as f32;
                    }
                }
            }
        }
        let mut ivf = Self {
            dim,
            centres,
            lists: vec![Cell::default(); cells],
            len: 0,
        };
        for i in 0..n {
            ivf.push(row(i), None);
        }
        ivf
    }

    pub fn len(&self) -> usize {
        self.len
    }

    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    pub fn cells(&self) -> usize {
        self.lists.len()
    }

    /// The cell of a context: its nearest centre (the first of equal ones).
    pub fn cell_of(&self, x: &[f32]) -> u32 {
        let mut sims = Vec::with_capacity(self.cells());
        scan_f32(&self.centres, x, self.dim, &mut sims);
        argmax(&sims) as u32
    }

    /// Files the next pool entry (its f32 context) in its cell (`cell`, when the caller has
    /// it from [`Ivf::candidates`] on the same context).
    pub fn push(&mut self, x: &[f32], cell: Option<u32>) {
        let c = cell.unwrap_or_else(|| self.cell_of(x)) as usize;
        debug_assert_eq!(c as u32, self.cell_of(x));
        let cell = &mut self.lists[c];
        cell.pos.push(self.len as u32);
        let s = quantise(x, &mut cell.codes);
        cell.scales.push(s);
        self.len += 1;
    }

    /// Keeps the entries with `keep[pos]`, renumbered in order (the pool's eviction).
    pub fn retain(&mut self, keep: &[bool]) {
        let mut new_pos = Vec::with_capacity(keep.len());
        let mut next = 0u32;
        for &k in keep {
            new_pos.push(next);
            next += k as u32;
        }
        let d = self.dim;
        for cell in &mut self.lists {
            let mut w = 0;
            for r in 0..cell.pos.len() {
                let p = cell.pos[r] as usize;
                if !keep[p] {
                    continue;
                }
                cell.pos[w] = new_pos[p];
                cell.scales[w] = cell.scales[r];
                if w != r {
                    cell.codes.copy_within(r * d..(r + 1) * d, w * d);
                }
                w += 1;
            }
            cell.pos.truncate(w);
            cell.scales.truncate(w);
            cell.codes.truncate(w * d);
        }
        self.len = next as usize;
    }

    /// The positions of the `ef` entries with the highest 8-bit cosine to `x` among the
    /// `probe` cells nearest to it (ties: the earlier position), in no particular order; and
    /// `x`'s own cell.
    pub fn candidates(&self, x: &[f32], probe: usize, ef: usize) -> (Vec<usize>, u32) {
        let plan = self.plan(x, probe, ef);
        let scored = (0..plan.cells.len()).map(|i| self.score_cell(&plan, i));
        (plan.select(scored), plan.own)
    }

    /// The first half of [`Ivf::candidates`]: `x`'s own cell, the cells to probe (best
    /// first) and its 8-bit code. The cells can then be scored in any order, on any thread
    /// ([`Ivf::score_cell`]), and [`Plan::select`] takes the same candidates from them.
    pub fn plan(&self, x: &[f32], probe: usize, ef: usize) -> Plan {
        let mut sims = Vec::with_capacity(self.cells());
        scan_f32(&self.centres, x, self.dim, &mut sims);
        let own = argmax(&sims) as u32;
        if self.is_empty() || ef == 0 {
            return Plan {
                own,
                cells: Vec::new(),
                q: Vec::new(),
                qs: 0.0,
                ef,
            };
        }
        let mut order: Vec<usize> = (0..self.cells()).collect();
        let probe = probe.clamp(1, order.len());
        let by_sim = |a: &usize, b: &usize| sims[*b].total_cmp(&sims[*a]).then(a.cmp(b));
        if probe < order.len() {
            order.select_nth_unstable_by(probe - 1, by_sim);
            order.truncate(probe);
        }
        let mut q = Vec::with_capacity(self.dim);
        let qs = quantise(x, &mut q);
        Plan {
            own,
            cells: order,
            q,
            qs,
            ef,
        }
    }

    /// The approximate similarities of the plan's `i`-th cell's entries, with their positions.
    pub fn score_cell(&self, plan: &Plan, i: usize) -> Vec<(f32, usize)> {
        let d = self.dim;
        let kind = dot_kind();
        let cell = &self.lists[plan.cells[i]];
        cell.pos
            .iter()
            .zip(&cell.scales)
            .zip(cell.codes.chunks_exact(d))
            .map(|((&p, &s), code)| {
                (
                    dot_i8_with(kind, &plan.q, code) as f32 * plan.qs * s,
                    p as usize,
                )
            })
            .collect()
    }
}

/// A query's probe of the index ([`Ivf::plan`]).
#[derive(Debug, Clone)]
pub struct Plan {
    /// The query's own cell.
    pub own: u32,
    /// The cells to probe.
    pub cells: Vec<usize>,
    q: Vec<i8>,
    qs: f32,
    ef: usize,
}

impl Plan {
    /// The `ef` best of the scored cells, given in the plan's cell order (so the same
    /// candidates, in the same order, whoever scored which cell).
    pub fn select(&self, scored: impl Iterator<Item = Vec<(f32, usize)>>) -> Vec<usize> {
        let ef = self.ef;
        if self.cells.is_empty() {
            return Vec::new();
        }
        let mut scored: Vec<(f32, usize)> = scored.flatten().collect();
        let cmp = |a: &(f32, usize), b: &(f32, usize)| b.0.total_cmp(&a.0).then(a.1.cmp(&b.1));
        if scored.len() > ef {
            scored.select_nth_unstable_by(ef - 1, cmp);
            scored.truncate(ef);
        }
        scored.into_iter().map(|(_, p)| p).collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every dot product this processor can run equals the plain sum, at every length
    /// (whole steps, tails, empty) and at the extremes of the codes.
    #[test]
    fn every_dot_product_kind_is_the_plain_sum() {
        let mut kinds = vec![DotKind::Portable];
        #[cfg(target_arch = "x86_64")]
        {
            if std::arch::is_x86_feature_detected!("avx2") {
                kinds.push(DotKind::Avx2);
            }
            if std::arch::is_x86_feature_detected!("avx512f")
                && std::arch::is_x86_feature_detected!("avx512bw")
                && std::arch::is_x86_feature_detected!("avx512vnni")
            {
                kinds.push(DotKind::Vnni);
            }
        }
        let mut state = 0x9e37_79b9u32;
        let mut next = move || {
            state ^= state << 13;
            state ^= state >> 17;
            state ^= state << 5;
            (state >> 24) as u8 as i8
        };
        for n in (0..=130).chain([255, 256, 511, 512, 513, 1024]) {
            let a: Vec<i8> = (0..n).map(|_| next()).collect();
            let b: Vec<i8> = (0..n).map(|_| next()).collect();
            let naive: i32 = a.iter().zip(&b).map(|(x, y)| *x as i32 * *y as i32).sum();
            for &k in &kinds {
                assert_eq!(dot_i8_with(k, &a, &b), naive, "n = {n}");
            }
        }
        for (x, y) in [(-128i8, -128i8), (-128, 127), (127, -128), (127, 127)] {
            let (a, b) = (vec![x; 1024], vec![y; 1024]);
            for &k in &kinds {
                assert_eq!(dot_i8_with(k, &a, &b), 1024 * x as i32 * y as i32);
            }
        }
    }

    #[test]
    fn codes_keep_the_cosine_and_dot_products_are_exact() {
        let x: Vec<f32> = (0..100)
            .map(|i| ((i * 37 % 23) as f32 - 11.0) / 40.0)
            .collect();
        let y: Vec<f32> = (0..100)
            .map(|i| ((i * 11 % 19) as f32 - 9.0) / 30.0)
            .collect();
        let (mut cx, mut cy) = (Vec::new(), Vec::new());
        let (sx, sy) = (quantise(&x, &mut cx), quantise(&y, &mut cy));
        let exact: f32 = x.iter().zip(&y).map(|(a, b)| a * b).sum();
        let approx = dot_i8_with(dot_kind(), &cx, &cy) as f32 * sx * sy;
        assert!(
            (exact - approx).abs() < 0.02 * exact.abs().max(1.0),
            "{exact} {approx}"
        );
        let naive: i32 = cx.iter().zip(&cy).map(|(a, b)| *a as i32 * *b as i32).sum();
        assert_eq!(dot_i8_with(dot_kind(), &cx, &cy), naive);
        assert_eq!(dot_i8_body(&cx, &cy), naive);
        // Extremes: 512 products of -127 * -127 stay far inside i32.
        let big = vec![-127i8; 512];
        assert_eq!(dot_i8_with(dot_kind(), &big, &big), 512 * 127 * 127);
    }
}
