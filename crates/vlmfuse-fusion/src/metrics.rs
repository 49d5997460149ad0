//! docs/PAPER-METHOD.md §7 metrics. A label with no true and no predicted positive scores F1 = 1 (tables say so).

use crate::signals::clip;
use crate::threshold::jaccard;
use serde::Serialize;

pub const ECE_BINS: usize = 10;

/// Accumulates rounds; `finish` turns the sums into [`Scores`].
#[derive(Debug, Clone)]
pub struct MetricsAcc {
    l: usize,
    eps: f64,
    rounds: usize,
    hamming: f64,
    jaccard: f64,
    tp: Vec<u64>,
    fp: Vec<u64>,
    fneg: Vec<u64>,
    brier: f64,
    log_loss: f64,
    probs: u64,
    /// Per bin: count, sum of predicted probability, sum of outcomes.
    bins: [(u64, f64, f64); ECE_BINS],
    latencies: Vec<f64>,
}

#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ReliabilityBin {
    pub lo: f64,
    pub hi: f64,
    pub count: u64,
    pub mean_predicted: f64,
    pub observed: f64,
}

#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Scores {
    pub rounds: usize,
    pub hamming: f64,
    pub micro_f1: f64,
    pub macro_f1: f64,
    pub jaccard: f64,
    pub brier: f64,
    pub log_loss: f64,
    pub ece: f64,
    /// Mean per-round latency in microseconds (fusion work only), if measured.
    pub latency_us: Option<f64>,
    pub latency_p95_us: Option<f64>,
    pub per_label_f1: Vec<f64>,
    pub reliability: Vec<ReliabilityBin>,
}

fn f1(tp: u64, fp: u64, fneg: u64) -> f64 {
    let den = 2 * tp + fp + fneg;
    if den == 0 {
        1.0
    } else {
        2.0 * tp as f64 / den as f64
    }
}

impl MetricsAcc {
    pub fn new(l: usize, eps: f64) -> Self {
        Self {
            l,
            eps,
            rounds: 0,
            hamming: 0.0,
            jaccard: 0.0,
            tp: vec![0; l],
            fp: vec![0; l],
            fneg: vec![0; l],
            brier: 0.0,
            log_loss: 0.0,
            probs: 0,
            bins: [(0, 0.0, 0.0); ECE_BINS],
            latencies: Vec::new(),
        }
    }

    /// Adds one scored round. `prob` are the probabilities behind `pred`; a hard baseline passes
    /// its 0/1 prediction, which the probability metrics then score as such (clipped to `eps`).
    pub fn add(&mut self, pred: &[u8], prob: &[f64], truth: &[u8], latency_s: Option<f64>) {
        self.rounds += 1;
        let mut wrong = 0usize;
        for k in 0..self.l {
            let (p, y) = (pred[k] != 0, truth[k] != 0);
            wrong += (p != y) as usize;
            match (p, y) {
                (true, true) => self.tp[k] += 1,
                (true, false) => self.fp[k] += 1,
                (false, true) => self.fneg[k] += 1,
                _ => {}
            }
            let q = prob[k];
            let yf = y as u8 as f64;
            self.brier += (q - yf) * (q - yf);
            let qc = clip(q, self.eps);
            self.log_loss -= if y { qc.ln() } else { (1.0 - qc).ln() };
            self.probs += 1;
            let b = ((q * ECE_BINS as f64).floor() as usize).min(ECE_BINS - 1);
            self.bins[b].0 += 1;
            self.bins[b].1 += q;
            self.bins[b].2 += yf;
        }
        self.hamming += wrong as f64 / self.l as f64;
        self.jaccard += jaccard(pred, truth);
        if let Some(t) = latency_s {
            self.latencies.push(t);
        }
    }

    pub fn finish(&self) -> Scores {
        let r = self.rounds.max(1) as f64;
        let np = self.probs.max(1) as f64;
        let per_label_f1: Vec<f64> = (0..self.l)
            .map(|k| f1(self.tp[k], self.fp[k], self.fneg[k]))
            .collect();
        let (tp, fp, fneg) = (
            self.tp.iter().sum(),
            self.fp.iter().sum(),
            self.fneg.iter().sum(),
        );
        let mut ece = 0.0;
        let reliability = self
            .bins
            .iter()
            .enumerate()
            .map(|(b, &(c, ps, ys))| {
                let (mp, obs) = if c == 0 {
                    (0.0, 0.0)
                } else {
                    (ps / c as f64, ys / c as f64)
                };
                ece += c as f64 / np * (obs - mp).abs();
                ReliabilityBin {
                    lo: b as f64 / ECE_BINS as f64,
                    hi: (b + 1) as f64 / ECE_BINS as f64,
                    count: c,
                    mean_predicted: mp,
                    observed: obs,
                }
            })
            .collect();
        let (latency_us, latency_p95_us) = if self.latencies.is_empty() {
            (None, None)
        } else {
            let mut l = self.latencies.clone();
            l.sort_by(f64::total_cmp);
            let mean = l.iter().sum::<f64>() / l.len() as f64;
            let p95 = l[((l.len() as f64 * 0.95).ceil() as usize).clamp(1, l.len()) - 1];
            (Some(mean * 1e6), Some(p95 * 1e6))
        };
        Scores {
            rounds: self.rounds,
            hamming: self.hamming / r,
            micro_f1: f1(tp, fp, fneg),
            macro_f1: per_label_f1.iter().sum::<f64>() / self.l.max(1) as f64,
            jaccard: self.jaccard / r,
            brier: self.brier / np,
            log_loss: self.log_loss / np,
            ece,
            latency_us,
            latency_p95_us,
            per_label_f1,
            reliability,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hand_computed_metrics() {
        let mut m = MetricsAcc::new(3, 1e-6);
        // Round 1: pred {0,1}, truth {0}: hamming 1/3, jaccard 1/2.
        m.add(&[1, 1, 0], &[0.9, 0.6, 0.1], &[1, 0, 0], None);
        // Round 2: pred {}, truth {2}: hamming 1/3, jaccard 0.
        m.add(&[0, 0, 0], &[0.2, 0.3, 0.4], &[0, 0, 1], None);
        let s = m.finish();
        assert!((s.hamming - 1.0 / 3.0).abs() < 1e-15);
        assert!((s.jaccard - 0.25).abs() < 1e-15);
        // tp=1 (label 0), fp=1 (label 1), fn=1 (label 2): micro = 2/(2+1+1) = 0.5.
        assert!((s.micro_f1 - 0.5).abs() < 1e-15);
        // Per label: 1.0, 0.0, 0.0 -> macro 1/3.
        assert_eq!(s.per_label_f1, vec![1.0, 0.0, 0.0]);
        assert!((s.macro_f1 - 1.0 / 3.0).abs() < 1e-15);
        let brier = (0.01 + 0.36 + 0.01 + 0.04 + 0.09 + 0.36) / 6.0;
        assert!((s.brier - brier).abs() < 1e-15);
        let ll =
            -(0.9f64.ln() + 0.4f64.ln() + 0.9f64.ln() + 0.8f64.ln() + 0.7f64.ln() + 0.4f64.ln())
                / 6.0;
        assert!((s.log_loss - ll).abs() < 1e-12);
        // Bins: 0.1 ->1 (y0), 0.2 ->2 (y0), 0.3 ->3 (y0), 0.4 ->4 (y1), 0.6 ->6 (y0), 0.9 ->9 (y1).
        let ece = (0.1 + 0.2 + 0.3 + 0.6 + 0.6 + 0.1) / 6.0;
        assert!((s.ece - ece).abs() < 1e-12, "{} vs {}", s.ece, ece);
    }

    #[test]
    fn a_label_never_true_nor_predicted_scores_one() {
        let mut m = MetricsAcc::new(2, 1e-6);
        m.add(&[1, 0], &[1.0, 0.0], &[1, 0], None);
        let s = m.finish();
        assert_eq!(s.per_label_f1, vec![1.0, 1.0]);
        assert_eq!(s.macro_f1, 1.0);
        assert_eq!(s.hamming, 0.0);
    }
}
