//! The labelled history `B` and its exact nearest-neighbour search (SPEC §2).
//!
//! Contexts are kept in f64 so that a similarity computed here equals, to rounding, the one an
//! independent f64 implementation computes: the posteriors must agree to 1e-9, and f32 storage
//! moves a cosine by about 1e-7. Entries are laid out flat (structure of arrays) so the scan over
//! the bank is one pass over contiguous memory.

use serde::{Deserialize, Serialize};
use std::cmp::Ordering;
use std::collections::BinaryHeap;

#[derive(Debug, Clone, Default, Serialize, Deserialize)]
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
    let mut acc = [0.0f64; 4];
    let ca = a.chunks_exact(4);
    let cb = b.chunks_exact(4);
    let (ra, rb) = (ca.remainder(), cb.remainder());
    for (x, y) in ca.zip(cb) {
        acc[0] += x[0] * y[0];
        acc[1] += x[1] * y[1];
        acc[2] += x[2] * y[2];
        acc[3] += x[3] * y[3];
    }
    let mut s = (acc[0] + acc[1]) + (acc[2] + acc[3]);
    for (x, y) in ra.iter().zip(rb) {
        s += x * y;
    }
    s
}

impl Bank {
    pub fn new(n: usize, l: usize) -> Self {
        Self {
            n,
            l,
            global: vec![[0; 4]; n * l],
            global_y: vec![0; l],
            ..Default::default()
        }
    }

    pub fn len(&self) -> usize {
        self.seqs.len()
    }

    pub fn is_empty(&self) -> bool {
        self.seqs.is_empty()
    }

    /// Context dimension, 0 while the bank is empty and no dimension was fixed.
    pub fn dim(&self) -> usize {
        self.dim
    }

    pub fn set_dim(&mut self, dim: usize) {
        debug_assert!(self.is_empty() || self.dim == dim);
        self.dim = dim;
    }

    pub fn context(&self, pos: usize) -> &[f64] {
        &self.contexts[pos * self.dim..(pos + 1) * self.dim]
    }

    pub fn seq(&self, pos: usize) -> u64 {
        self.seqs[pos]
    }

    pub fn present(&self, pos: usize, i: usize) -> bool {
        self.present[pos * self.n + i] != 0
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
        self.contexts.extend_from_slice(context);
        self.seqs.push(seq);
        for (i, &p) in present.iter().enumerate() {
            self.present.push(p as u8);
            for k in 0..self.l {
                let r = if p { reports[i * self.l + k] } else { 0 };
                self.reports.push(r);
                if p {
                    let y = truth[k];
                    let cell = match (r, y) {
                        (1, 1) => 0,
                        (0, 1) => 1,
                        (1, 0) => 2,
                        _ => 3,
                    };
                    self.global[i * self.l + k][cell] += 1;
                }
            }
        }
        for (k, &y) in truth.iter().enumerate() {
            self.truths.push(y);
            self.global_y[k] += y as u64;
        }
    }

    /// Cosine similarity of a unit-norm query to every entry, in bank order.
    pub fn similarities(&self, x: &[f64], out: &mut Vec<f64>) {
        out.clear();
        out.reserve(self.len());
        if self.dim == 0 {
            return;
        }
        out.extend(self.contexts.chunks_exact(self.dim).map(|c| dot(x, c)));
    }

    /// The `m` most similar entries, best first; equal similarities put the older round first.
    /// `sims` are the similarities in bank order (from [`Bank::similarities`] or a batched GEMM).
    pub fn top(&self, sims: &[f64], m: usize) -> Vec<Neighbour> {
        debug_assert_eq!(sims.len(), self.len());
        let m = m.min(self.len());
        if m == 0 {
            return Vec::new();
        }
        let mut heap: BinaryHeap<Worst> = BinaryHeap::with_capacity(m + 1);
        for (pos, &sim) in sims.iter().enumerate() {
            let seq = self.seqs[pos];
            if heap.len() < m {
                heap.push(Worst { sim, seq, pos });
                continue;
            }
            let worst = heap.peek().expect("heap holds m > 0 entries");
            let better = sim > worst.sim || (sim == worst.sim && seq < worst.seq);
            if better {
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
}

#[cfg(test)]
mod tests {
    use super::*;

    fn unit(v: &[f64]) -> Vec<f64> {
        let n = v.iter().map(|x| x * x).sum::<f64>().sqrt();
        v.iter().map(|x| x / n).collect()
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
