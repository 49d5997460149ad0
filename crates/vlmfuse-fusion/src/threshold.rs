//! The decision threshold (PAPER-METHOD.md §3): the grid point that maximises the mean per-round Jaccard
//! index over the posteriors that the last `threshold_window` labelled rounds got at inference.
//!
//! Refitting after every labelled round must stay cheap, so each round contributes a per-grid-point
//! score vector that is added when it enters the window and subtracted when it leaves. In global
//! mode a round's Jaccard index is a fraction with a denominator of at most `L`; scaled by
//! `lcm(1..=L)` it is an integer, so the window sums are exact integers and never drift however
//! many rounds slide through. (For very large ontologies, where that lcm overflows, the sums are
//! recomputed in f64 from the window instead.)

use crate::config::{FusionConfig, ThresholdMode};
use std::collections::VecDeque;

#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
pub struct ThresholdFitter {
    mode: ThresholdMode,
    grid: Vec<f64>,
    l: usize,
    window: usize,
    min_rounds: usize,
    initial: f64,
    tie: f64,
    labelled: u64,
    rounds: VecDeque<(Vec<f64>, Vec<u8>)>,
    /// Global mode, exact path: `lcm(1..=L)` and per-grid-point sums of `J * lcm`.
    lcm: Option<i128>,
    sums: Vec<i128>,
    /// Per-label mode: per label and grid point `[tp, fp, fn]`.
    counts: Vec<[i64; 3]>,
    current: Vec<f64>,
}

fn gcd(a: i128, b: i128) -> i128 {
    if b == 0 {
        a
    } else {
        gcd(b, a % b)
    }
}

/// `lcm(1..=l)` if it and a window's worth of sums fit in an i128.
fn lcm_upto(l: usize, window: usize) -> Option<i128> {
    let mut acc: i128 = 1;
    for v in 1..=l as i128 {
        acc = (acc / gcd(acc, v)).checked_mul(v)?;
    }
    acc.checked_mul(window as i128 + 1)?;
    Some(acc)
}

impl ThresholdFitter {
    pub fn new(cfg: &FusionConfig, l: usize) -> Self {
        let grid = cfg.threshold_grid();
        let g = grid.len();
        let lcm = match cfg.threshold_mode {
            ThresholdMode::Global => lcm_upto(l, cfg.threshold_window),
            ThresholdMode::PerLabel => None,
        };
        Self {
            mode: cfg.threshold_mode,
            l,
            window: cfg.threshold_window,
            min_rounds: cfg.threshold_min_rounds,
            initial: cfg.threshold_initial,
            tie: cfg.threshold_tie,
            labelled: 0,
            rounds: VecDeque::new(),
            lcm,
            sums: vec![0; g],
            counts: match cfg.threshold_mode {
                ThresholdMode::PerLabel => vec![[0; 3]; l * g],
                ThresholdMode::Global => Vec::new(),
            },
            current: vec![cfg.threshold_initial; l],
            grid,
        }
    }

    /// The threshold per label (all equal in global mode).
    pub fn thresholds(&self) -> &[f64] {
        &self.current
    }

    /// The global threshold (the first label's in per-label mode).
    pub fn scalar(&self) -> f64 {
        self.current[0]
    }

    pub fn mode(&self) -> ThresholdMode {
        self.mode
    }

    /// For every label, how many grid points lie at or below its posterior: the label is
    /// predicted at grid index `g` exactly when `g < cut[k]`.
    fn cuts(&self, q: &[f64]) -> Vec<usize> {
        q.iter()
            .map(|&p| self.grid.partition_point(|&t| t <= p))
            .collect()
    }

    /// Global mode: the round's Jaccard index at every grid point as `(intersection, union)`.
    fn jaccard_parts(&self, q: &[f64], y: &[u8]) -> Vec<(i64, i64)> {
        let g = self.grid.len();
        let cuts = self.cuts(q);
        // pred[g] = #{k: cut_k > g}; inter[g] = #{k: y_k = 1, cut_k > g}.
        let mut pred_hist = vec![0i64; g + 1];
        let mut inter_hist = vec![0i64; g + 1];
        // Labels of unknown truth (partial feedback) are not part of the round's label set:
        // neither predicted nor true, they leave its Jaccard index alone.
        for (k, &c) in cuts.iter().enumerate() {
            if y[k] > 1 {
                continue;
            }
            pred_hist[c] += 1;
            if y[k] != 0 {
                inter_hist[c] += 1;
            }
        }
        let truth = y.iter().filter(|&&v| v == 1).count() as i64;
        let mut out = vec![(0, 0); g];
        let (mut pred, mut inter) = (0i64, 0i64);
        for gi in (0..g).rev() {
            pred += pred_hist[gi + 1];
            inter += inter_hist[gi + 1];
            out[gi] = (inter, pred + truth - inter);
        }
        out
    }

    fn add_global(&mut self, q: &[f64], y: &[u8], sign: i128) {
        let lcm = self.lcm.expect("exact path");
        for (gi, (i, u)) in self.jaccard_parts(q, y).into_iter().enumerate() {
            let scaled = if u == 0 {
                lcm
            } else {
                i as i128 * (lcm / u as i128)
            };
            self.sums[gi] += sign * scaled;
        }
    }

    fn add_per_label(&mut self, q: &[f64], y: &[u8], sign: i64) {
        let g = self.grid.len();
        let cuts = self.cuts(q);
        for k in 0..self.l {
            if y[k] > 1 {
                continue;
            }
            let row = &mut self.counts[k * g..(k + 1) * g];
            for (gi, c) in row.iter_mut().enumerate() {
                let pred = gi < cuts[k];
                match (pred, y[k] != 0) {
                    (true, true) => c[0] += sign,
                    (true, false) => c[1] += sign,
                    (false, true) => c[2] += sign,
                    (false, false) => {}
                }
            }
        }
    }

    /// The lowest grid index whose score is within `tie` of the best.
    fn pick(&self, scores: impl Iterator<Item = f64> + Clone) -> usize {
        let best = scores.clone().fold(f64::NEG_INFINITY, f64::max);
        scores
            .enumerate()
            .find(|(_, s)| *s >= best - self.tie)
            .map(|(i, _)| i)
            .unwrap_or(0)
    }

    /// Mean per-round Jaccard at every grid point over the window (global mode).
    pub fn mean_jaccard(&self) -> Vec<f64> {
        let n = self.rounds.len().max(1) as f64;
        match self.lcm {
            Some(lcm) => self
                .sums
                .iter()
                .map(|&s| s as f64 / (lcm as f64 * n))
                .collect(),
            None => {
                let mut acc = vec![0.0f64; self.grid.len()];
                for (q, y) in &self.rounds {
                    for (gi, (i, u)) in self.jaccard_parts(q, y).into_iter().enumerate() {
                        acc[gi] += if u == 0 { 1.0 } else { i as f64 / u as f64 };
                    }
                }
                acc.iter().map(|s| s / n).collect()
            }
        }
    }

    /// Takes in one labelled round's inference-time posteriors and refits.
    pub fn push(&mut self, q: &[f64], y: &[u8]) {
        self.labelled += 1;
        self.rounds.push_back((q.to_vec(), y.to_vec()));
        match (self.mode, self.lcm) {
            (ThresholdMode::Global, Some(_)) => self.add_global(q, y, 1),
            (ThresholdMode::PerLabel, _) => self.add_per_label(q, y, 1),
            _ => {}
        }
        if self.rounds.len() > self.window {
            let (oq, oy) = self.rounds.pop_front().expect("non-empty window");
            match (self.mode, self.lcm) {
                (ThresholdMode::Global, Some(_)) => self.add_global(&oq, &oy, -1),
                (ThresholdMode::PerLabel, _) => self.add_per_label(&oq, &oy, -1),
                _ => {}
            }
        }
        if (self.labelled as usize) < self.min_rounds {
            self.current = vec![self.initial; self.l];
            return;
        }
        match self.mode {
            ThresholdMode::Global => {
                let scores = self.mean_jaccard();
                let t = self.grid[self.pick(scores.iter().copied())];
                self.current = vec![t; self.l];
            }
            ThresholdMode::PerLabel => {
                let g = self.grid.len();
                for k in 0..self.l {
                    let row = &self.counts[k * g..(k + 1) * g];
                    let scores = row.iter().map(|c| {
                        let den = c[0] + c[1] + c[2];
                        if den == 0 {
                            1.0
                        } else {
                            c[0] as f64 / den as f64
                        }
                    });
                    self.current[k] = self.grid[self.pick(scores)];
                }
            }
        }
    }
}

/// The Jaccard index of one round's prediction against its truth; 1 when both are empty.
pub fn jaccard(pred: &[u8], truth: &[u8]) -> f64 {
    let (mut i, mut u) = (0usize, 0usize);
    for (&p, &y) in pred.iter().zip(truth) {
        i += (p != 0 && y != 0) as usize;
        u += (p != 0 || y != 0) as usize;
    }
    if u == 0 {
        1.0
    } else {
        i as f64 / u as f64
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A direct, slow implementation of the docs/PAPER-METHOD.md rule to compare against.
    fn brute(cfg: &FusionConfig, window: &[(Vec<f64>, Vec<u8>)]) -> f64 {
        let grid = cfg.threshold_grid();
        let scores: Vec<f64> = grid
            .iter()
            .map(|&t| {
                window
                    .iter()
                    .map(|(q, y)| {
                        let pred: Vec<u8> = q.iter().map(|&p| (p >= t) as u8).collect();
                        jaccard(&pred, y)
                    })
                    .sum::<f64>()
                    / window.len() as f64
            })
            .collect();
        let best = scores.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        grid[scores.iter().position(|&s| s >= best - 1e-12).unwrap()]
    }

    fn lcg(state: &mut u64) -> f64 {
        *state = state
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (*state >> 11) as f64 / (1u64 << 53) as f64
    }

    #[test]
    fn initial_until_min_rounds_then_matches_brute_force_with_sliding_window() {
        let cfg = FusionConfig {
            threshold_window: 30,
            ..Default::default()
        };
        let l = 14;
        let mut f = ThresholdFitter::new(&cfg, l);
        let mut all = Vec::new();
        let mut s = 7u64;
        for r in 0..120 {
            let y: Vec<u8> = (0..l).map(|_| (lcg(&mut s) < 0.2) as u8).collect();
            let q: Vec<f64> = y
                .iter()
                .map(|&v| (0.6 * v as f64 + 0.5 * lcg(&mut s)).min(1.0))
                .collect();
            f.push(&q, &y);
            all.push((q, y));
            if r + 1 < 20 {
                assert_eq!(f.scalar(), 0.5);
            } else {
                let lo = all.len().saturating_sub(30);
                assert_eq!(f.scalar(), brute(&cfg, &all[lo..]), "round {r}");
            }
        }
    }

    #[test]
    fn ties_go_to_the_lowest_threshold() {
        // One round, truth {0}, q = [0.9, 0.1]: every t in (0.1, 0.9] scores 1; lowest is 0.105.
        let cfg = FusionConfig {
            threshold_min_rounds: 1,
            ..Default::default()
        };
        let mut f = ThresholdFitter::new(&cfg, 2);
        f.push(&[0.9, 0.1], &[1, 0]);
        assert_eq!(f.scalar(), 0.105);
    }

    #[test]
    fn empty_truth_and_empty_prediction_score_one() {
        assert_eq!(jaccard(&[0, 0], &[0, 0]), 1.0);
        assert_eq!(jaccard(&[1, 0], &[0, 0]), 0.0);
        assert_eq!(jaccard(&[1, 1], &[1, 0]), 0.5);
    }

    #[test]
    fn per_label_mode_fits_each_label() {
        let cfg = FusionConfig {
            threshold_min_rounds: 1,
            threshold_mode: ThresholdMode::PerLabel,
            ..Default::default()
        };
        let mut f = ThresholdFitter::new(&cfg, 2);
        f.push(&[0.7, 0.3], &[1, 1]);
        f.push(&[0.2, 0.25], &[0, 0]);
        // Label 0 separates in (0.2, 0.7]; label 1 in (0.25, 0.3].
        assert_eq!(f.thresholds(), &[0.205, 0.255]);
    }

    #[test]
    fn fallback_path_agrees_with_exact_path() {
        let cfg = FusionConfig::default();
        let mut exact = ThresholdFitter::new(&cfg, 5);
        let mut float = ThresholdFitter::new(&cfg, 5);
        float.lcm = None;
        let mut s = 3u64;
        for _ in 0..50 {
            let y: Vec<u8> = (0..5).map(|_| (lcg(&mut s) < 0.3) as u8).collect();
            let q: Vec<f64> = (0..5).map(|_| lcg(&mut s)).collect();
            exact.push(&q, &y);
            float.push(&q, &y);
            assert_eq!(exact.scalar(), float.scalar());
        }
    }
}
