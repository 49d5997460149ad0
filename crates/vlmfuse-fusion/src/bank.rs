//! The labelled history `B` and its exact nearest-neighbour search (PAPER-METHOD.md §2).
//!
//! Contexts are kept in f64 so that a similarity computed here equals, to rounding, the one an
//! independent f64 implementation computes: the posteriors must agree to 1e-9, and f32 storage
//! moves a cosine by about 1e-7. Entries are laid out flat (structure of arrays) so the scan over
//! the bank is one pass over contiguous memory.

use std::cmp::Ordering;
use std::collections::BinaryHeap;

#[derive(Debug, Clone, Default, serde::Serialize, serde::Deserialize)]
pub struct Bank {
    n: usize,
    l: usize,
    dim: usize,
    contexts: Vec<f64>,
    /// Round sequence numbers: ties in similarity go to the older round (smaller sequence).
    seqs: Vec<u64>,
    /// `n` presence flags per entry.
    present: Vec<u8>,
    /// `n * L` reports per entry (0 where the reporter was absent).
    reports: Vec<u8>,
    /// `L` truths per entry.
    truths: Vec<u8>,
    /// Whole-bank counts for the `no-context` ablation, per reporter and label:
    /// `[r*y, (1-r)*y, r*(1-y), (1-r)*(1-y)]` over the entries where the reporter was present.
    global: Vec<[u64; 4]>,
    /// Whole-bank positives per label.
    global_y: Vec<u64>,
    /// Whole-bank entries whose truth is known, per label (partial feedback leaves some
    /// unknown; with every label known it is the bank's length).
    global_known: Vec<u64>,
    /// f32 copy of every context for a fast first pass over the bank (half the memory traffic
    /// of the f64 scan), with the exact norm of each entry's rounding error, which bounds how far
    /// the fast similarity can be from the exact one (Cauchy-Schwarz). See [`Bank::top_exact`].
    mirror: Vec<f32>,
    mirror_err: Vec<f64>,
    /// Contexts kept only as their f32 copy, which is then the context itself (exact cosines
    /// are computed against it widened to f64): a third of the memory. The `adaptive` pool's
    /// bank; the paper method's keeps f64 (PAPER-METHOD.md's numbers to 1e-9).
    #[serde(default)]
    compact: bool,
}

/// Below this many entries the exact f64 scan is cheap enough on its own (at 1,000 entries of
/// d = 512 the f32 first pass halves a scan: `vlmfuse bench --banks 1000`).
const PREFILTER_MIN: usize = 512;

/// f32 dot product, sixteen lanes wide so it vectorises.
#[inline(always)]
fn dot_f32_body(a: &[f32], b: &[f32]) -> f32 {
    let mut acc = [0.0f32; 16];
    let ca = a.chunks_exact(16);
    let cb = b.chunks_exact(16);
    let (ra, rb) = (ca.remainder(), cb.remainder());
    for (x, y) in ca.zip(cb) {
        for l in 0..16 {
            acc[l] += x[l] * y[l];
        }
    }
    let mut s: f32 = acc.iter().sum();
    for (x, y) in ra.iter().zip(rb) {
        s += x * y;
    }
    s
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn dot_f32_avx2(a: &[f32], b: &[f32]) -> f32 {
    dot_f32_body(a, b)
}

/// One row's f32 dot product, AVX2 + FMA where the processor has them (chosen at run time).
#[inline]
fn dot_f32_fast(a: &[f32], b: &[f32]) -> f32 {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma") {
        // SAFETY: the features this function is compiled for were just detected.
        return unsafe { dot_f32_avx2(a, b) };
    }
    dot_f32_body(a, b)
}

/// A unit-norm query rounded to f32 for a first pass, with what bounds the first pass's error:
/// the rounding of the query itself, its norm, and the f32 accumulation.
struct F32Query {
    xq: Vec<f32>,
    err: f64,
    norm: f64,
    acc: f64,
}

impl F32Query {
    fn new(x: &[f64], dim: usize) -> Self {
        let xq: Vec<f32> = x.iter().map(|&v| v as f32).collect();
        let err = x
            .iter()
            .zip(&xq)
            .map(|(&a, &b)| (a - b as f64).powi(2))
            .sum::<f64>()
            .sqrt();
        let norm = xq.iter().map(|&v| (v as f64).powi(2)).sum::<f64>().sqrt();
        // f32 arithmetic: each product and each addition rounds by at most u relative, so the
        // sum is off by at most (d + 2) u * ||x~_j|| * ||xq||; 4d + 16 leaves a wide margin.
        let u = f32::EPSILON as f64 / 2.0;
        let acc = (4 * dim + 16) as f64 * u;
        F32Query { xq, err, norm, acc }
    }

    /// A rigorous bound on |f32 first pass - exact cosine| for an entry whose f32 copy is off
    /// its context by `ej`.
    #[inline]
    fn bound(&self, ej: f64) -> f64 {
        let xn = 1.0 + ej;
        ej + self.err * xn + self.acc * xn * self.norm + 1e-12
    }
}

/// Fills `out[j]` with the f32 similarity of every entry (AVX2 + FMA where the processor has
/// them, chosen at run time; the portable loop elsewhere).
pub(crate) fn scan_f32(mirror: &[f32], x: &[f32], dim: usize, out: &mut Vec<f32>) {
    out.clear();
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma") {
        // SAFETY: the features this function is compiled for were just detected.
        out.extend(
            mirror
                .chunks_exact(dim)
                .map(|c| unsafe { dot_f32_avx2(c, x) }),
        );
        return;
    }
    out.extend(mirror.chunks_exact(dim).map(|c| dot_f32_body(c, x)));
}

/// A compact bank's [`Bank::sim`] of `x` to each of the entries `pos`, on its rows (`dim`
/// f32 each) held apart from the bank ([`Bank::take_rows`]): the same function, so the same
/// bits.
pub fn sims_in(rows: &[f32], dim: usize, x: &[f64], pos: &[usize], out: &mut Vec<f64>) {
    out.extend(
        pos.iter()
            .map(|&j| dot_f32(x, &rows[j * dim..(j + 1) * dim])),
    );
}

/// One neighbour: position in the bank and cosine similarity.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Neighbour {
    pub pos: usize,
    pub sim: f64,
}

/// Heap entry ordered so that the *worst* kept neighbour is on top: lower similarity is worse,
/// and at equal similarity the newer round (larger sequence) is worse.
#[derive(PartialEq)]
struct Worst {
    sim: f64,
    seq: u64,
    pos: usize,
}
impl Eq for Worst {}
impl PartialOrd for Worst {
    fn partial_cmp(&self, other: &Self) -> Option<Ordering> {
        Some(self.cmp(other))
    }
}
impl Ord for Worst {
    fn cmp(&self, other: &Self) -> Ordering {
        // "Greater" = worse = popped first.
        other
            .sim
            .total_cmp(&self.sim)
            .then_with(|| self.seq.cmp(&other.seq))
    }
}

/// Dot product with four accumulators so the compiler vectorises it; the order of a sum of
/// products changes it only by rounding.
#[inline]
pub fn dot(a: &[f64], b: &[f64]) -> f64 {
    dot_with(a, b)
}

/// [`dot`] of an f64 query with an f32 entry widened to f64, in the same order.
#[inline]
pub fn dot_f32(a: &[f64], b: &[f32]) -> f64 {
    dot_with(a, b)
}

/// Lanes of the exact dot product: element `i` of each full block of `DOT_LANES` goes to lane
/// `i % DOT_LANES`. Four lanes made each product a chain of `d / 4` dependent additions (at
/// d = 512 the exact cosines of a scan's survivors cost a tenth of an `adaptive` round); sixteen
/// are four AVX2 registers.
const DOT_LANES: usize = 16;

/// The one summation order of every exact similarity (so that f64 and f32 banks differ only by
/// their values, and every path gives the same bits): sixteen interleaved accumulators over
/// the full blocks, added pairwise (lane `j` with `j + 8`, then `+ 4`, `+ 2`, `+ 1`), then the
/// tail in order. AVX2 where the processor has it (no FMA: the same multiplies and adds).
#[inline(always)]
fn dot_with<T: Copy + Into<f64>>(a: &[f64], b: &[T]) -> f64 {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: the feature this function is compiled for was just detected.
        return unsafe { dot_with_avx2(a, b) };
    }
    dot_with_body(a, b)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn dot_with_avx2<T: Copy + Into<f64>>(a: &[f64], b: &[T]) -> f64 {
    dot_with_body(a, b)
}

#[inline(always)]
fn dot_with_body<T: Copy + Into<f64>>(a: &[f64], b: &[T]) -> f64 {
    let mut acc = [0.0f64; DOT_LANES];
    let ca = a.chunks_exact(DOT_LANES);
    let cb = b.chunks_exact(DOT_LANES);
    let (ra, rb) = (ca.remainder(), cb.remainder());
    for (x, y) in ca.zip(cb) {
        for j in 0..DOT_LANES {
            acc[j] += x[j] * y[j].into();
        }
    }
    let mut width = DOT_LANES / 2;
    while width > 0 {
        for j in 0..width {
            acc[j] += acc[j + width];
        }
        width /= 2;
    }
    let mut s = acc[0];
    for (x, y) in ra.iter().zip(rb) {
        s += x * (*y).into();
    }
    s
}

/// The `global` cell of a report `r` against a truth `y`: `[r*y, (1-r)*y, r*(1-y),
/// (1-r)*(1-y)]`.
#[inline]
fn cell(r: u8, y: u8) -> usize {
    match (r, y) {
        (1, 1) => 0,
        (0, 1) => 1,
        (1, 0) => 2,
        _ => 3,
    }
}

impl Bank {
    pub fn new(n: usize, l: usize) -> Self {
        Self {
            n,
            l,
            global: vec![[0; 4]; n * l],
            global_y: vec![0; l],
            global_known: vec![0; l],
            ..Default::default()
        }
    }

    /// A bank that keeps contexts only as f32 (see `compact`).
    pub fn new_compact(n: usize, l: usize) -> Self {
        Self {
            compact: true,
            ..Self::new(n, l)
        }
    }

    /// The exact cosine of a unit-norm query to entry `pos` (against its f32 copy in a compact
    /// bank).
    #[inline]
    pub fn sim(&self, x: &[f64], pos: usize) -> f64 {
        if self.compact {
            dot_f32(x, &self.mirror[pos * self.dim..(pos + 1) * self.dim])
        } else {
            dot(x, self.context(pos))
        }
    }

    /// [`Bank::sim`] of `x` to each of the entries `pos`, into `out` in that order.
    pub fn sims(&self, x: &[f64], pos: &[usize], out: &mut Vec<f64>) {
        out.clear();
        if self.compact {
            sims_in(&self.mirror, self.dim, x, pos, out);
        } else {
            out.extend(pos.iter().map(|&j| self.sim(x, j)));
        }
    }

    /// Takes a compact bank's rows out (`None` for a bank that keeps f64 contexts), so that
    /// another thread can score candidates against them ([`sims_in`]) while work that never
    /// reads a context goes on; [`Bank::put_rows`] gives them back before anything else.
    pub fn take_rows(&mut self) -> Option<Vec<f32>> {
        self.compact.then(|| std::mem::take(&mut self.mirror))
    }

    /// Gives back the rows [`Bank::take_rows`] took.
    pub fn put_rows(&mut self, rows: Option<Vec<f32>>) {
        if let Some(rows) = rows {
            debug_assert!(self.mirror.is_empty());
            self.mirror = rows;
        }
    }

    pub fn len(&self) -> usize {
        self.seqs.len()
    }

    pub fn is_empty(&self) -> bool {
        self.seqs.is_empty()
    }

    pub fn set_dim(&mut self, dim: usize) {
        debug_assert!(self.is_empty() || self.dim == dim);
        self.dim = dim;
    }

    /// The f64 context of entry `pos`; not kept by a compact bank (use [`Bank::sim`]).
    pub fn context(&self, pos: usize) -> &[f64] {
        debug_assert!(!self.compact, "a compact bank keeps no f64 contexts");
        &self.contexts[pos * self.dim..(pos + 1) * self.dim]
    }

    /// Every entry's f32 copy, in bank order.
    pub fn f32_rows(&self) -> &[f32] {
        &self.mirror
    }

    pub fn dim(&self) -> usize {
        self.dim
    }

    /// The f32 copy of entry `pos`'s context (the context itself in a compact bank).
    pub fn f32_row(&self, pos: usize) -> &[f32] {
        &self.mirror[pos * self.dim..(pos + 1) * self.dim]
    }

    pub fn seq(&self, pos: usize) -> u64 {
        self.seqs[pos]
    }

    /// Entry `pos`'s presence flags, `n` of them.
    pub fn present_of(&self, pos: usize) -> &[u8] {
        &self.present[pos * self.n..(pos + 1) * self.n]
    }

    pub fn present(&self, pos: usize, i: usize) -> bool {
        self.present[pos * self.n + i] != 0
    }

    /// Entry `pos`'s reports, `n * L` of them.
    pub fn reports_of(&self, pos: usize) -> &[u8] {
        &self.reports[pos * self.n * self.l..(pos + 1) * self.n * self.l]
    }

    pub fn report(&self, pos: usize, i: usize, k: usize) -> u8 {
        self.reports[(pos * self.n + i) * self.l + k]
    }

    pub fn truth(&self, pos: usize, k: usize) -> u8 {
        self.truths[pos * self.l + k]
    }

    pub fn global_counts(&self, i: usize, k: usize) -> [u64; 4] {
        self.global[i * self.l + k]
    }

    pub fn global_positives(&self, k: usize) -> u64 {
        self.global_y[k]
    }

    /// Entries whose truth for label `k` is known.
    pub fn global_known(&self, k: usize) -> u64 {
        self.global_known[k]
    }

    /// Adds (`sign = 1`) or removes (`-1`) entry `pos`'s known truths from the whole-bank
    /// counts.
    fn count(&mut self, pos: usize, sign: i64) {
        let (n, l) = (self.n, self.l);
        let add = |c: &mut u64| *c = c.wrapping_add_signed(sign);
        for k in 0..l {
            let y = self.truths[pos * l + k];
            if y > 1 {
                continue;
            }
            for i in 0..n {
                if self.present[pos * n + i] != 0 {
                    let r = self.reports[(pos * n + i) * l + k];
                    add(&mut self.global[i * l + k][cell(r, y)]);
                }
            }
            if y == 1 {
                add(&mut self.global_y[k]);
            }
            add(&mut self.global_known[k]);
        }
    }

    /// A later feedback on entry `pos`: every label `truth` knows (0 or 1) takes that value,
    /// the others keep theirs. The whole-bank counts follow.
    pub fn merge_truth(&mut self, pos: usize, truth: &[u8]) {
        self.count(pos, -1);
        let l = self.l;
        for (k, &y) in truth.iter().enumerate() {
            if y <= 1 {
                self.truths[pos * l + k] = y;
            }
        }
        self.count(pos, 1);
    }

    /// Appends a labelled round. The context must already be unit-norm and of the bank's
    /// dimension; the engine checks both before it gets here.
    pub fn push(
        &mut self,
        seq: u64,
        context: &[f64],
        present: &[bool],
        reports: &[u8],
        truth: &[u8],
    ) {
        if self.is_empty() && self.dim == 0 {
            self.dim = context.len();
        }
        debug_assert_eq!(context.len(), self.dim);
        if self.compact {
            // The f32 copy is the context: no rounding error to bound.
            self.mirror.extend(context.iter().map(|&v| v as f32));
            self.mirror_err.push(0.0);
        } else {
            self.contexts.extend_from_slice(context);
            self.push_mirror(context);
        }
        self.seqs.push(seq);
        for (i, &p) in present.iter().enumerate() {
            self.present.push(p as u8);
            for k in 0..self.l {
                let r = if p { reports[i * self.l + k] } else { 0 };
                self.reports.push(r);
            }
        }
        self.truths.extend_from_slice(truth);
        self.count(self.len() - 1, 1);
    }

    /// Keeps the entries with `keep[pos]` true, in order (the bounded pool's eviction). The
    /// whole-bank counts are recomputed from the kept entries.
    pub fn retain(&mut self, keep: &[bool]) {
        debug_assert_eq!(keep.len(), self.len());
        let (d, n, l) = (self.dim, self.n, self.l);
        let mut w = 0;
        for (r, &k) in keep.iter().enumerate() {
            if !k {
                continue;
            }
            if w != r {
                if !self.compact {
                    self.contexts.copy_within(r * d..(r + 1) * d, w * d);
                }
                self.mirror.copy_within(r * d..(r + 1) * d, w * d);
                self.mirror_err[w] = self.mirror_err[r];
                self.seqs[w] = self.seqs[r];
                self.present.copy_within(r * n..(r + 1) * n, w * n);
                self.reports
                    .copy_within(r * n * l..(r + 1) * n * l, w * n * l);
                self.truths.copy_within(r * l..(r + 1) * l, w * l);
            }
            w += 1;
        }
        if !self.compact {
            self.contexts.truncate(w * d);
        }
        self.mirror.truncate(w * d);
        self.mirror_err.truncate(w);
        self.seqs.truncate(w);
        self.present.truncate(w * n);
        self.reports.truncate(w * n * l);
        self.truths.truncate(w * l);
        self.global = vec![[0; 4]; n * l];
        self.global_y = vec![0; l];
        self.global_known = vec![0; l];
        for pos in 0..w {
            self.count(pos, 1);
        }
    }

    fn push_mirror(&mut self, x: &[f64]) {
        let mut err = 0.0f64;
        for &v in x {
            let f = v as f32;
            self.mirror.push(f);
            err += (v - f as f64).powi(2);
        }
        self.mirror_err.push(err.sqrt());
    }

    /// The `m` most similar entries to a unit-norm query, best first, exactly as
    /// [`Bank::top`] over exact f64 similarities would rank them, but reading half the
    /// memory for large banks.
    ///
    /// A first pass computes every entry's similarity from its f32 copy, with a rigorous bound
    /// `b_j` on the difference to the exact cosine: `||x - x~_j||` (stored) plus the query's own
    /// f32 rounding and the f32 accumulation error (about 3e-5 at d = 512). An entry whose upper bound falls below the
    /// m-th best lower bound cannot be among the m best, so only the survivors (typically a few
    /// more than m) are re-scored exactly in f64 and ranked with the usual tie rule.
    pub fn top_exact(&self, x: &[f64], m: usize) -> Vec<Neighbour> {
        let n = self.len();
        let m = m.min(n);
        if m == 0 {
            return Vec::new();
        }
        let first_pass = if n <= 4 * m {
            None
        } else {
            self.approx_with_bounds(x)
        };
        let Some((approx, bound)) = first_pass else {
            let mut sims = Vec::new();
            self.similarities(x, &mut sims);
            return self.top(&sims, m);
        };
        let mut lo: Vec<f64> = (0..n).map(|j| approx[j] as f64 - bound[j]).collect();
        let (_, &mut cut, _) = lo.select_nth_unstable_by(m - 1, |a, b| b.total_cmp(a));
        let mut cand: Vec<usize> = Vec::with_capacity(4 * m);
        for (j, &a) in approx.iter().enumerate() {
            if a as f64 + bound[j] >= cut {
                cand.push(j);
            }
        }
        self.select(cand.into_iter().map(|j| (j, self.sim(x, j))), m)
    }

    /// [`Bank::top_exact`] over the entries `pos` only (distinct positions): the `m` most
    /// similar of them, best first, exactly as an f64 ranking of their [`Bank::sim`]s would
    /// give. With many more of them than `m`, an f32 first pass (eight lanes a step where the
    /// processor has them) with the same rigorous bound keeps only the entries that can reach
    /// the `m`-th best for the exact score: the `adaptive` switch's `paper` candidate searches
    /// its labelled window this way on every labelled round.
    pub fn top_among(&self, x: &[f64], pos: &[usize], m: usize) -> Vec<Neighbour> {
        self.top_among_known(x, pos, m, None, None)
    }

    /// [`Bank::top_among`] reusing what a scan of the same query over the whole bank already
    /// computed: `first`, its f32 first pass (`(approx, bound)` from
    /// [`Bank::approx_with_bounds`]; used when it covers every entry of `pos`), the same values
    /// the pass here would compute; `known`, its exact cosines (`known[j]` is
    /// [`Bank::sim`]`(x, j)` where not NaN), the same function. So the same bits and the same
    /// result; only the survivors not already scored are scored here.
    pub fn top_among_known(
        &self,
        x: &[f64],
        pos: &[usize],
        m: usize,
        first: Option<(&[f32], &[f64])>,
        known: Option<&[f64]>,
    ) -> Vec<Neighbour> {
        let sim = |j: usize| match known.and_then(|k| k.get(j)) {
            Some(&v) if !v.is_nan() => v,
            _ => self.sim(x, j),
        };
        let m = m.min(pos.len());
        if m == 0 {
            return Vec::new();
        }
        if pos.len() <= 4 * m || self.mirror.len() != self.len() * self.dim {
            return self.select(pos.iter().map(|&j| (j, sim(j))), m);
        }
        let approx: Vec<(f64, f64)> = match first {
            Some((a, b)) if pos.iter().all(|&j| j < a.len() && j < b.len()) => {
                pos.iter().map(|&j| (a[j] as f64, b[j])).collect()
            }
            _ => {
                let q = F32Query::new(x, self.dim);
                let d = self.dim;
                pos.iter()
                    .map(|&j| {
                        let a = dot_f32_fast(&self.mirror[j * d..(j + 1) * d], &q.xq);
                        (a as f64, q.bound(self.mirror_err[j]))
                    })
                    .collect()
            }
        };
        let mut lo: Vec<f64> = approx.iter().map(|&(a, b)| a - b).collect();
        let (_, &mut cut, _) = lo.select_nth_unstable_by(m - 1, |a, b| b.total_cmp(a));
        let survivors = pos
            .iter()
            .zip(&approx)
            .filter(|(_, &(a, b))| a + b >= cut)
            .map(|(&j, _)| (j, sim(j)));
        self.select(survivors, m)
    }

    /// The f32 first pass of [`Bank::top_exact`] on its own: every entry's approximate cosine to
    /// a unit-norm query and a rigorous bound on its distance to the exact one, for callers that
    /// rank by something else than the cosine (the `adaptive` pool ranks by decayed kernel
    /// weight). `None` when the bank is small enough that exact similarities are as cheap.
    pub fn approx_with_bounds(&self, x: &[f64]) -> Option<(Vec<f32>, Vec<f64>)> {
        let n = self.len();
        if n < PREFILTER_MIN || self.mirror.len() != n * self.dim {
            return None;
        }
        let q = F32Query::new(x, self.dim);
        let mut approx = Vec::with_capacity(n);
        scan_f32(&self.mirror, &q.xq, self.dim, &mut approx);
        let bounds = self.mirror_err.iter().map(|&ej| q.bound(ej)).collect();
        Some((approx, bounds))
    }

    /// Keeps the `m` best `(position, similarity)` pairs, best first: higher similarity wins, and
    /// at equal similarity the older round (smaller sequence).
    pub(crate) fn select(
        &self,
        items: impl Iterator<Item = (usize, f64)>,
        m: usize,
    ) -> Vec<Neighbour> {
        let mut heap: BinaryHeap<Worst> = BinaryHeap::with_capacity(m + 1);
        for (pos, sim) in items {
            let seq = self.seqs[pos];
            if heap.len() < m {
                heap.push(Worst { sim, seq, pos });
                continue;
            }
            let worst = heap.peek().expect("heap holds m > 0 entries");
            if sim > worst.sim || (sim == worst.sim && seq < worst.seq) {
                heap.pop();
                heap.push(Worst { sim, seq, pos });
            }
        }
        // into_sorted_vec is ascending in "worseness": best first.
        heap.into_sorted_vec()
            .into_iter()
            .map(|w| Neighbour {
                pos: w.pos,
                sim: w.sim,
            })
            .collect()
    }

    /// Cosine similarity of a unit-norm query to every entry, in bank order.
    pub fn similarities(&self, x: &[f64], out: &mut Vec<f64>) {
        out.clear();
        out.reserve(self.len());
        if self.dim == 0 {
            return;
        }
        if self.compact {
            out.extend(self.mirror.chunks_exact(self.dim).map(|c| dot_f32(x, c)));
        } else {
            out.extend(self.contexts.chunks_exact(self.dim).map(|c| dot(x, c)));
        }
    }

    /// The `m` most similar entries, best first; equal similarities put the older round first.
    /// `sims` are the similarities in bank order (from [`Bank::similarities`] or a batched GEMM).
    pub fn top(&self, sims: &[f64], m: usize) -> Vec<Neighbour> {
        debug_assert_eq!(sims.len(), self.len());
        let m = m.min(self.len());
        if m == 0 {
            return Vec::new();
        }
        self.select(sims.iter().copied().enumerate(), m)
    }

    /// Like [`Bank::top`], with the similarities indexed by each entry's sequence number
    /// instead of its position: `sims[seq]` for every `seq` the bank holds (a batched GEMM's row
    /// over every earlier round, whichever of them the bank kept).
    pub fn top_by_seq(&self, sims: &[f64], m: usize) -> Vec<Neighbour> {
        let m = m.min(self.len());
        if m == 0 {
            return Vec::new();
        }
        self.select(
            self.seqs
                .iter()
                .enumerate()
                .map(|(pos, &s)| (pos, sims[s as usize])),
            m,
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn unit(v: &[f64]) -> Vec<f64> {
        let n = v.iter().map(|x| x * x).sum::<f64>().sqrt();
        v.iter().map(|x| x / n).collect()
    }

    /// The dispatched dot products (AVX2 here when the processor has it) are the portable
    /// loop's bit for bit, and the plain sum's to rounding.
    #[test]
    fn every_path_of_the_dot_product_gives_the_same_bits() {
        let mut state = 0x9e37_79b9_7f4a_7c15u64;
        let mut rnd = move || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state >> 11) as f64 / (1u64 << 53) as f64 - 0.5
        };
        for dim in [0usize, 1, 7, 15, 16, 17, 31, 32, 33, 512, 515] {
            let a: Vec<f64> = (0..dim).map(|_| rnd()).collect();
            let b: Vec<f64> = (0..dim).map(|_| rnd()).collect();
            let b32: Vec<f32> = b.iter().map(|&v| v as f32).collect();
            assert_eq!(
                dot(&a, &b).to_bits(),
                dot_with_body(&a, &b).to_bits(),
                "{dim}"
            );
            assert_eq!(
                dot_f32(&a, &b32).to_bits(),
                dot_with_body(&a, &b32).to_bits(),
                "{dim}"
            );
            let plain: f64 = a.iter().zip(&b).map(|(x, y)| x * y).sum();
            assert!((dot(&a, &b) - plain).abs() < 1e-13, "{dim}");
        }
    }

    /// The batched cosines, in the bank or on its rows taken out, are `sim`'s bit for bit.
    #[test]
    fn batched_similarities_are_sim_bit_for_bit() {
        let mut state = 0x2545_f491_4f6c_dd1du64;
        let mut rnd = move || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state >> 11) as f64 / (1u64 << 53) as f64 - 0.5
        };
        for dim in [1usize, 3, 4, 5, 8, 31, 512, 515] {
            for compact in [true, false] {
                let mut b = if compact {
                    Bank::new_compact(2, 1)
                } else {
                    Bank::new(2, 1)
                };
                for s in 0..23u64 {
                    let v: Vec<f64> = (0..dim).map(|_| rnd()).collect();
                    b.push(s, &unit(&v), &[true, false], &[1, 0], &[1]);
                }
                let x = unit(&(0..dim).map(|_| rnd()).collect::<Vec<_>>());
                for count in [0usize, 1, 3, 4, 5, 8, 11, 23] {
                    let pos: Vec<usize> = (0..count).map(|i| (i * 7 + 3) % 23).collect();
                    let mut got = vec![f64::NAN; 2];
                    b.sims(&x, &pos, &mut got);
                    let want: Vec<u64> = pos.iter().map(|&j| b.sim(&x, j).to_bits()).collect();
                    let bits = |v: &[f64]| v.iter().map(|v| v.to_bits()).collect::<Vec<u64>>();
                    assert_eq!(
                        bits(&got),
                        want,
                        "dim {dim}, compact {compact}, {count} entries"
                    );
                    let rows = b.take_rows();
                    assert_eq!(rows.is_some(), compact);
                    if let Some(rows) = &rows {
                        let mut apart = Vec::new();
                        sims_in(rows, dim, &x, &pos, &mut apart);
                        assert_eq!(bits(&apart), want, "dim {dim}, {count} entries, apart");
                    }
                    b.put_rows(rows);
                }
            }
        }
    }

    #[test]
    fn top_k_orders_by_similarity_then_age() {
        let mut b = Bank::new(1, 1);
        // seq 10 and seq 5 share a context: the tie must go to seq 5 (older).
        b.push(10, &unit(&[1.0, 0.0]), &[true], &[1], &[1]);
        b.push(5, &unit(&[1.0, 0.0]), &[true], &[1], &[1]);
        b.push(7, &unit(&[0.0, 1.0]), &[true], &[1], &[1]);
        b.push(8, &unit(&[1.0, 1.0]), &[true], &[1], &[1]);
        let mut sims = Vec::new();
        b.similarities(&unit(&[1.0, 0.1]), &mut sims);
        let top = b.top(&sims, 2);
        assert_eq!(top.iter().map(|n| n.pos).collect::<Vec<_>>(), vec![1, 0]);
        let top1 = b.top(&sims, 1);
        assert_eq!(top1[0].pos, 1, "older round wins the tie");
        let all = b.top(&sims, 10);
        assert_eq!(
            all.iter().map(|n| n.pos).collect::<Vec<_>>(),
            vec![1, 0, 3, 2]
        );
    }

    #[test]
    fn top_k_matches_a_full_sort() {
        let mut b = Bank::new(1, 1);
        let mut state = 12345u64;
        let mut rnd = || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((state >> 11) as f64 / (1u64 << 53) as f64) - 0.5
        };
        for s in 0..300u64 {
            // Quantised coordinates make many exact ties.
            let v: Vec<f64> = (0..3).map(|_| (rnd() * 4.0).round()).collect();
            let v = if v.iter().all(|x| *x == 0.0) {
                vec![1.0, 0.0, 0.0]
            } else {
                v
            };
            b.push(1000 - s, &unit(&v), &[true], &[0], &[0]);
        }
        let q = unit(&[0.3, -0.2, 0.9]);
        let mut sims = Vec::new();
        b.similarities(&q, &mut sims);
        let mut idx: Vec<usize> = (0..b.len()).collect();
        idx.sort_by(|&a, &c| sims[c].total_cmp(&sims[a]).then(b.seq(a).cmp(&b.seq(c))));
        let got: Vec<usize> = b.top(&sims, 50).iter().map(|n| n.pos).collect();
        assert_eq!(got, idx[..50].to_vec());
    }

    #[test]
    fn prefiltered_top_k_equals_exact_top_k() {
        let mut state = 99u64;
        let mut rnd = || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((state >> 11) as f64 / (1u64 << 53) as f64) - 0.5
        };
        let d = 40;
        let mut b = Bank::new(1, 1);
        let centres: Vec<Vec<f64>> = (0..5).map(|_| (0..d).map(|_| rnd()).collect()).collect();
        for s in 0..5000u64 {
            let c = &centres[(s % 5) as usize];
            // Every 7th entry duplicates an earlier one exactly: ties must go to the older.
            let v: Vec<f64> = if s % 7 == 6 {
                b.context((s / 2) as usize).to_vec()
            } else {
                c.iter().map(|x| x + 0.2 * rnd()).collect()
            };
            b.push(s, &unit(&v), &[true], &[0], &[0]);
        }
        for qi in 0..20 {
            let q = unit(
                &centres[qi % 5]
                    .iter()
                    .map(|x| x + 0.2 * rnd())
                    .collect::<Vec<_>>(),
            );
            let mut sims = Vec::new();
            b.similarities(&q, &mut sims);
            for m in [1, 10, 50, 120] {
                assert_eq!(b.top_exact(&q, m), b.top(&sims, m), "query {qi} m {m}");
            }
            // Over a subset (every third entry and the duplicates, out of order): the exact
            // ranking of that subset.
            let mut subset: Vec<usize> = (0..5000).filter(|j| j % 3 == 0 || j % 7 == 6).collect();
            subset.reverse();
            assert!(
                b.mirror.len() == b.len() * b.dim,
                "the first pass is not exercised"
            );
            let (approx, bound) = b.approx_with_bounds(&q).expect("a first pass");
            for m in [1, 10, 50, 120] {
                let brute = b.select(subset.iter().map(|&j| (j, sims[j])), m);
                assert_eq!(b.top_among(&q, &subset, m), brute, "query {qi} m {m}");
                // Reusing the whole bank's first pass gives the same; so does a pass that
                // misses some positions searched (it is then not used).
                let first = Some((approx.as_slice(), bound.as_slice()));
                assert_eq!(
                    b.top_among_known(&q, &subset, m, first, None),
                    brute,
                    "reused {qi} {m}"
                );
                // Exact cosines known for some entries (a scan's survivors) give the same.
                let known: Vec<f64> = (0..5000)
                    .map(|j| if j % 5 == 0 { b.sim(&q, j) } else { f64::NAN })
                    .collect();
                assert_eq!(
                    b.top_among_known(&q, &subset, m, first, Some(&known)),
                    brute,
                    "known {qi} {m}"
                );
                let short = Some((&approx[..4000], &bound[..4000]));
                assert_eq!(
                    b.top_among_known(&q, &subset, m, short, None),
                    brute,
                    "short {qi} {m}"
                );
            }
            // And it is used: a made-up pass (later entries "closer", no error) decides.
            let fake: Vec<f32> = (0..5000).map(|j| j as f32 / 5000.0).collect();
            let zero = vec![0.0; 5000];
            let got = b.top_among_known(&q, &subset, 10, Some((&fake, &zero)), None);
            assert!(got.iter().all(|n| n.pos >= 4900), "{got:?}");
        }
        // A query equal to a stored context finds it (and its older duplicate first).
        let q = b.context(4000).to_vec();
        let mut sims = Vec::new();
        b.similarities(&q, &mut sims);
        assert_eq!(b.top_exact(&q, 5), b.top(&sims, 5));
    }

    #[test]
    fn global_counts_follow_presence() {
        let mut b = Bank::new(2, 2);
        b.push(0, &[1.0], &[true, false], &[1, 0, 1, 1], &[1, 0]);
        assert_eq!(b.global_counts(0, 0), [1, 0, 0, 0]);
        assert_eq!(b.global_counts(0, 1), [0, 0, 0, 1]);
        assert_eq!(
            b.global_counts(1, 0),
            [0, 0, 0, 0],
            "absent reporter counts nothing"
        );
        assert_eq!(b.report(0, 1, 0), 0);
        assert_eq!(b.global_positives(0), 1);
    }
}
