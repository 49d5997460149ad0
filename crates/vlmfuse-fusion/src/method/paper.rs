//! `method = "paper"`: docs/PAPER-METHOD.md §1–7 to the letter. Its state is the labelled bank `B`, the
//! correlation window and the threshold fitter; unlabelled rounds change nothing.

use super::Ctx;
use crate::bank::{Bank, Neighbour};
use crate::config::FusionConfig;
use crate::corr::CorrWindow;
use crate::engine::{Inference, LabelledRound, Round};
use crate::signals::Signals;
use crate::threshold::ThresholdFitter;

#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
pub struct Paper {
    bank: Bank,
    corr: CorrWindow,
    threshold: ThresholdFitter,
    /// Bank position by round `seq`, for the first `indexed` entries: a later (partial)
    /// feedback finds its round's entry in O(1) instead of scanning the bank on every feedback
    /// (which made a replay quadratic). Derived from the bank, so not serialised: a snapshot
    /// read back rebuilds it at its first feedback.
    #[serde(skip)]
    by_seq: std::collections::HashMap<u64, usize>,
    #[serde(skip)]
    indexed: usize,
}

impl Paper {
    pub fn new(cfg: &FusionConfig, n: usize, l: usize) -> Self {
        Self {
            bank: Bank::new(n, l),
            corr: CorrWindow::new(n, l, cfg.corr_window),
            threshold: ThresholdFitter::new(cfg, l),
            by_seq: std::collections::HashMap::new(),
            indexed: 0,
        }
    }

    pub fn set_dim(&mut self, d: usize) {
        self.bank.set_dim(d);
    }

    pub fn bank(&self) -> &Bank {
        &self.bank
    }

    pub fn threshold(&self) -> &ThresholdFitter {
        &self.threshold
    }

    /// Infers a round (PAPER-METHOD.md §2–3). `sims`, when given, are the round's similarities to earlier
    /// rounds indexed by `seq` (a batched GEMM's row); else the bank is searched.
    pub fn infer(&self, cx: &Ctx, round: &Round, sims: Option<&[f64]>) -> Inference {
        let cfg = cx.cfg;
        let m = cfg.k.max(cfg.k_prior);
        let nb = if self.bank.is_empty() || cfg.ablations.no_context {
            Vec::new()
        } else {
            match sims {
                Some(s) => self.bank.top_by_seq(s, m),
                None => self.bank.top_exact(&round.context, m),
            }
        };
        let signals = self.signals(cx, round, &nb);
        let q = signals.full_posterior();
        let thresholds = self.threshold.thresholds().to_vec();
        Inference::decide(signals, q, thresholds, cx.w, None)
    }

    fn signals(&self, cx: &Ctx, round: &Round, nb: &[Neighbour]) -> Signals {
        signals(cx, round, &self.bank, &self.corr, nb)
    }

    /// A labelled round joins the bank and the correlation window, and the threshold is refitted
    /// on the posteriors it got at inference. A later (partial) feedback on a round already in
    /// the bank merges its labels into that entry; the windows take the new labels as one more
    /// entry (the labels an override replaced stay in them until they slide out).
    pub fn apply(&mut self, lr: &LabelledRound) {
        let r = &lr.round;
        for pos in self.indexed..self.bank.len() {
            self.by_seq.insert(self.bank.seq(pos), pos);
        }
        match self.by_seq.get(&lr.seq) {
            Some(&pos) => self.bank.merge_truth(pos, &lr.truth),
            None => {
                self.by_seq.insert(lr.seq, self.bank.len());
                self.bank
                    .push(lr.seq, &r.context, &r.present, &r.reports, &lr.truth)
            }
        }
        self.indexed = self.bank.len();
        self.corr.push(&r.present, &r.reports, &lr.truth);
        self.threshold.push(&lr.q, &lr.truth);
    }
}

/// The paper's inputs of a round (PAPER-METHOD.md §2–3): reliabilities and prior from its
/// labelled neighbours `nb` (best first) in `bank`, the guardrail's correlations from `corr`, the
/// reputations in force. Shared with `adaptive`'s `paper` candidate, which runs the same rule on
/// the labelled entries of its pool.
pub(crate) fn signals(
    cx: &Ctx,
    round: &Round,
    bank: &Bank,
    corr: &CorrWindow,
    nb: &[Neighbour],
) -> Signals {
    let cfg = cx.cfg;
    let l = cx.l;
    let coalition = round.coalition();
    let p = coalition.len();
    let mut theta_pos = vec![0.5; p * l];
    let mut theta_neg = vec![0.5; p * l];
    // Empty bank: docs/PAPER-METHOD.md fixes theta and pi at 0.5 (no signal), whatever the Beta priors.
    let mut prior = vec![0.5; l];
    if !bank.is_empty() {
        // Sums a+, b+, a-, b- per member and label, and kernel mass and positives for pi.
        let mut acc = vec![[0.0f64; 4]; p * l];
        // Kernel mass per label: with partial feedback an entry counts only toward the
        // labels whose truth it knows (with every label known, the same sum for each).
        let mut pi_mass = vec![0.0; l];
        let mut pi_pos = vec![0.0; l];
        if cfg.ablations.no_context {
            for (a, &i) in coalition.iter().enumerate() {
                for k in 0..l {
                    let c = bank.global_counts(i, k);
                    acc[a * l + k] = [c[0] as f64, c[1] as f64, c[2] as f64, c[3] as f64];
                }
            }
            for k in 0..l {
                pi_mass[k] = bank.global_known(k) as f64;
                pi_pos[k] = bank.global_positives(k) as f64;
            }
        } else {
            let kappa: Vec<f64> = nb.iter().map(|n| n.sim.max(0.0).powf(cfg.tau)).collect();
            for (idx, n) in nb.iter().enumerate().take(cfg.k) {
                let kp = kappa[idx];
                for (a, &i) in coalition.iter().enumerate() {
                    if !bank.present(n.pos, i) {
                        continue;
                    }
                    for k in 0..l {
                        let r = bank.report(n.pos, i, k);
                        let y = bank.truth(n.pos, k);
                        let cell = match (r, y) {
                            (_, 2..) => continue,
                            (1, 1) => 0,
                            (0, 1) => 1,
                            (1, 0) => 2,
                            _ => 3,
                        };
                        acc[a * l + k][cell] += kp;
                    }
                }
            }
            for (idx, n) in nb.iter().enumerate().take(cfg.k_prior) {
                for k in 0..l {
                    match bank.truth(n.pos, k) {
                        0 => pi_mass[k] += kappa[idx],
                        1 => {
                            pi_mass[k] += kappa[idx];
                            pi_pos[k] += kappa[idx];
                        }
                        _ => {}
                    }
                }
            }
        }
        for (idx, c) in acc.iter().enumerate() {
            let (ap, bp) = (cfg.alpha0 + c[0], cfg.beta0 + c[1]);
            let (an, bn) = (cfg.alpha0 + c[2], cfg.beta0 + c[3]);
            theta_pos[idx] = ap / (ap + bp);
            theta_neg[idx] = an / (an + bn);
        }
        for k in 0..l {
            prior[k] =
                (cfg.prior_alpha + pi_pos[k]) / (cfg.prior_alpha + cfg.prior_beta + pi_mass[k]);
        }
    }
    let mut rho = vec![0.0; p * p * l];
    if !cfg.ablations.no_guardrail {
        for a in 0..p {
            for b in 0..p {
                if a == b {
                    continue;
                }
                for k in 0..l {
                    rho[(a * p + b) * l + k] = corr.rho(coalition[a], coalition[b], k, cfg.rho_max);
                }
            }
        }
    }
    let mut reports = Vec::with_capacity(p * l);
    for &i in &coalition {
        reports.extend_from_slice(&round.reports[i * l..(i + 1) * l]);
    }
    let w = coalition.iter().map(|&i| cx.w[i]).collect();
    Signals {
        l,
        coalition,
        theta_pos,
        theta_neg,
        rho,
        prior,
        reports,
        w,
        eps: cfg.eps,
    }
}
