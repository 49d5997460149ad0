//! Pairwise error correlations `rho_ijk` over a sliding window (PAPER-METHOD.md §3).
//!
//! Each reporter pair keeps its own window of the last `W` labelled rounds in which *both* were
//! present, plus the running 2x2 counts of `(e_i, e_j)` per label, so reading `rho` is O(1) and
//! advancing the window is O(L) per pair. Counts are integers, so the window never drifts.

use std::collections::VecDeque;

#[derive(Debug, Clone, Default, serde::Serialize, serde::Deserialize)]
struct PairWindow {
    /// One code per label per round: `e_i + 2 * e_j`.
    rounds: VecDeque<Vec<u8>>,
    /// Per label, counts indexed by the code above: `[00, 10, 01, 11]` as `(e_i, e_j)`.
    counts: Vec<[u32; 4]>,
}

#[derive(Debug, Clone, Default, serde::Serialize, serde::Deserialize)]
pub struct CorrWindow {
    n: usize,
    l: usize,
    window: usize,
    pairs: Vec<PairWindow>,
}

/// Index of the unordered pair `{i, j}`, `i != j`, among the `n (n-1) / 2` pairs.
pub(crate) fn pair_index(n: usize, i: usize, j: usize) -> usize {
    let (a, b) = if i < j { (i, j) } else { (j, i) };
    a * n - a * (a + 1) / 2 + (b - a - 1)
}

/// The phi coefficient of a 2x2 table with every cell smoothed by +0.5, floored at 0 and capped.
pub fn smoothed_phi(c: [u32; 4], rho_max: f64) -> f64 {
    smoothed_phi_f64(
        [c[0] as f64, c[1] as f64, c[2] as f64, c[3] as f64],
        rho_max,
    )
}

/// [`smoothed_phi`] of a table of (expected, weighted) counts.
pub fn smoothed_phi_f64(c: [f64; 4], rho_max: f64) -> f64 {
    smoothed_phi_signed(c).clamp(0.0, rho_max)
}

/// The phi coefficient of a 2x2 table `[00, 10, 01, 11]` with every cell smoothed by +0.5, sign
/// kept and uncapped (in (-1, 1)).
pub fn smoothed_phi_signed(c: [f64; 4]) -> f64 {
    let n00 = c[0] + 0.5;
    let n10 = c[1] + 0.5;
    let n01 = c[2] + 0.5;
    let n11 = c[3] + 0.5;
    let num = n11 * n00 - n10 * n01;
    let den = ((n11 + n10) * (n01 + n00) * (n11 + n01) * (n10 + n00)).sqrt();
    num / den
}

/// A window entry's code for a label whose truth the feedback did not give.
const SKIP: u8 = u8::MAX;

impl CorrWindow {
    pub fn new(n: usize, l: usize, window: usize) -> Self {
        let pairs = (0..n * n.saturating_sub(1) / 2)
            .map(|_| PairWindow {
                rounds: VecDeque::new(),
                counts: vec![[0; 4]; l],
            })
            .collect();
        Self {
            n,
            l,
            window,
            pairs,
        }
    }

    /// `rho_ijk`, already floored at 0 and capped at `rho_max`.
    pub fn rho(&self, i: usize, j: usize, k: usize, rho_max: f64) -> f64 {
        smoothed_phi(self.pairs[pair_index(self.n, i, j)].counts[k], rho_max)
    }

    /// Raw counts `[00, 10, 01, 11]` of `(e_i, e_j)` for label `k` (for tests and statistics).
    pub fn counts(&self, i: usize, j: usize, k: usize) -> [u32; 4] {
        let c = self.pairs[pair_index(self.n, i, j)].counts[k];
        if i < j {
            c
        } else {
            [c[0], c[2], c[1], c[3]]
        }
    }

    /// Rounds currently in the window of pair `{i, j}`.
    pub fn len(&self, i: usize, j: usize) -> usize {
        self.pairs[pair_index(self.n, i, j)].rounds.len()
    }

    /// Advances every pair whose two reporters were both present in this labelled round.
    pub fn push(&mut self, present: &[bool], reports: &[u8], truth: &[u8]) {
        let l = self.l;
        for i in 0..self.n {
            if !present[i] {
                continue;
            }
            for j in i + 1..self.n {
                if !present[j] {
                    continue;
                }
                let pw = &mut self.pairs[pair_index(self.n, i, j)];
                // A label whose truth is unknown (partial feedback) is no evidence about the
                // pair's errors: coded SKIP, it never enters the counts.
                let codes: Vec<u8> = (0..l)
                    .map(|k| {
                        if truth[k] > 1 {
                            return SKIP;
                        }
                        let ei = (reports[i * l + k] != truth[k]) as u8;
                        let ej = (reports[j * l + k] != truth[k]) as u8;
                        ei + 2 * ej
                    })
                    .collect();
                for (k, &c) in codes.iter().enumerate() {
                    if c != SKIP {
                        pw.counts[k][c as usize] += 1;
                    }
                }
                pw.rounds.push_back(codes);
                if pw.rounds.len() > self.window {
                    let old = pw.rounds.pop_front().expect("window is non-empty");
                    for (k, &c) in old.iter().enumerate() {
                        if c != SKIP {
                            pw.counts[k][c as usize] -= 1;
                        }
                    }
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pair_indices_are_a_bijection() {
        let n = 6;
        let mut seen = std::collections::HashSet::new();
        for i in 0..n {
            for j in i + 1..n {
                let p = pair_index(n, i, j);
                assert_eq!(p, pair_index(n, j, i));
                assert!(p < n * (n - 1) / 2);
                assert!(seen.insert(p));
            }
        }
    }

    #[test]
    fn phi_by_hand() {
        // Empty window: every cell 0.5, phi = 0.
        assert_eq!(smoothed_phi([0, 0, 0, 0], 0.9), 0.0);
        // 3 rounds both wrong, 1 both right: cells 11=3.5, 00=1.5, 10=01=0.5.
        // phi = (3.5*1.5 - 0.25) / sqrt(4 * 2 * 4 * 2) = 5 / 8 = 0.625.
        assert!((smoothed_phi([1, 0, 0, 3], 0.9) - 0.625).abs() < 1e-15);
        // Perfectly anti-correlated errors are floored at 0.
        assert_eq!(smoothed_phi([0, 5, 5, 0], 0.9), 0.0);
        // Strong correlation is capped at rho_max.
        assert_eq!(smoothed_phi([100, 0, 0, 100], 0.9), 0.9);
    }

    #[test]
    fn window_slides_and_skips_absent_pairs() {
        let mut w = CorrWindow::new(3, 1, 2);
        // Reporters 0 and 1 both wrong; 2 absent.
        w.push(&[true, true, false], &[1, 1, 0], &[0]);
        assert_eq!(w.counts(0, 1, 0), [0, 0, 0, 1]);
        assert_eq!(w.len(0, 2), 0);
        // 0 wrong, 1 right.
        w.push(&[true, true, true], &[1, 0, 0], &[0]);
        assert_eq!(w.counts(0, 1, 0), [0, 1, 0, 1]);
        assert_eq!(w.counts(1, 0, 0), [0, 0, 1, 1], "swapped view");
        // Third round pushes the first out of the window of 2.
        w.push(&[true, true, true], &[0, 0, 0], &[0]);
        assert_eq!(w.counts(0, 1, 0), [1, 1, 0, 0]);
        assert_eq!(w.len(0, 2), 2);
    }
}
