//! The `adaptive` fusion method (docs/METHOD.md): SPEC's context-aware Dawid–Skene, extended
//! where the paper lists future work.
//!
//! - Every observed round joins the pool. An unlabelled round's truth is its E-step posterior
//!   (soft truth); a label overrides it. Reliabilities and the prior are kernel-weighted over
//!   neighbours with these soft truths, so unlabelled rounds teach.
//! - Local reliabilities are shrunk toward each reporter's whole-pool reliability, which is
//!   shrunk toward a cold prior that says "better than chance": with no labels the method is a
//!   reputation-weighted vote, never "every label on".
//! - The fused logit is Platt-scaled per label (calibrated posteriors), the threshold is fitted
//!   on the calibrated posteriors.
//! - Evidence decays with a half-life in labelled rounds; reputations mix in a fixed share so no
//!   reporter starves.
//!
//! The state is a pure function of the sequence of events (`observe`, `apply`), so replaying
//! stored rounds in order rebuilds it exactly. The per-event work is bounded: one pass over the
//! bank (as SPEC's inference does), the E-step of at most `refresh_max + em_chunk` entries.

pub mod calibrate;
pub mod config;
pub mod pool;

pub use calibrate::Calibrator;
pub use config::{AdaptiveConfig, Guardrail, Reputation, SoftTruth, WeightNorm};
pub use pool::{Nb, Pool, Scan};

use crate::corr::{pair_index, smoothed_phi_f64};
use crate::engine::{Engine, FeedbackOutcome, Inference, LabelledRound, Round};
use crate::error::FusionError;
use crate::signals::{clip, sigmoid, Signals};
use serde::{Deserialize, Serialize};

/// Whole-pool sums behind the hierarchical prior, decayed to a base clock: the decayed weight of
/// an entry observed at clock `c` is `2^((c - base) / h)` here, and `2^(-(now - base) / h)` times
/// that at clock `now`. Rebased (recomputed) when `now - base` exceeds `REBASE_HALF_LIVES`.
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
pub struct GlobalSums {
    base: u64,
    /// Per reporter and label: `[r t, (1-r) t, r (1-t), (1-r)(1-t)]` weighted sums.
    cells: Vec<[f64; 4]>,
    /// Per label: weighted sum of soft truths.
    pos: Vec<f64>,
    mass: f64,
    /// Per reporter pair and label: counts `[00, 10, 01, 11]` of the error indicators
    /// `(e_i, e_j)` over the labelled entries (the `pool` guardrail).
    pairs: Vec<[f64; 4]>,
    /// Incremental updates since the last rebuild: after as many as the pool has entries, the
    /// sums are rebuilt to clear the rounding that adding and removing accumulates (amortised
    /// O(n L) per update).
    updates: usize,
    /// The unlabelled weight the sums were built with (it ramps with the labels, so the sums
    /// are rebuilt when it has moved; see `global_refresh`).
    unlabelled: f64,
}

const REBASE_HALF_LIVES: f64 = 40.0;
const UNLABELLED_REBUILD: f64 = 0.1;

/// The adaptive method's state beside SPEC's (which it shares: reputations, correlation window,
/// threshold fitter, statistics).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Adaptive {
    pub(crate) pool: Pool,
    pub(crate) calib: Calibrator,
    pub(crate) global: GlobalSums,
    /// Next pool position the per-event EM visits.
    cursor: usize,
    /// Unlabelled entries re-estimated so far (a statistic).
    em_updates: u64,
    pub(crate) credit: CreditState,
    /// Decisions of the model and of majority vote scored on the labelled rounds (the vote
    /// fallback serves the vote until the model has done better on both counts).
    model_score: Tally,
    vote_score: Tally,
}

/// True positives, false positives and false negatives of a stream of decisions.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Tally {
    pub tp: u64,
    pub fp: u64,
    pub fneg: u64,
}

impl Tally {
    fn add(&mut self, pred: bool, y: bool) {
        match (pred, y) {
            (true, true) => self.tp += 1,
            (true, false) => self.fp += 1,
            (false, true) => self.fneg += 1,
            _ => {}
        }
    }

    /// Hamming errors.
    pub fn errors(&self) -> u64 {
        self.fp + self.fneg
    }

    /// Micro-F1 (1 with no positive at all).
    pub fn f1(&self) -> f64 {
        let den = 2 * self.tp + self.fp + self.fneg;
        if den == 0 {
            1.0
        } else {
            2.0 * self.tp as f64 / den as f64
        }
    }
}

/// What the reputation update remembers of past credits.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct CreditState {
    /// Decayed sum of the per-round mean `|phi|` and its decayed count: the credit scale.
    scale_num: f64,
    scale_den: f64,
    /// Per reporter: discounted sum of scaled credits and discounted count of its rounds.
    sum: Vec<f64>,
    count: Vec<f64>,
}

impl CreditState {
    /// The typical `|phi|` (1 until a round has been credited).
    pub fn scale(&self) -> f64 {
        if self.scale_den > 0.0 {
            self.scale_num / self.scale_den
        } else {
            1.0
        }
    }

    /// Each reporter's recent mean scaled credit.
    pub fn mean_credit(&self) -> Vec<f64> {
        self.sum
            .iter()
            .zip(&self.count)
            .map(|(s, c)| if *c > 0.0 { s / c } else { 0.0 })
            .collect()
    }
}

impl Adaptive {
    pub fn new(cfg: &crate::FusionConfig, n: usize, l: usize) -> Self {
        let a = &cfg.adaptive;
        let rank_half_life = if a.decay_ranking { a.half_life } else { 0.0 };
        let mut pool = Pool::new(n, l, cfg.k.max(cfg.k_prior), cfg.tau, rank_half_life);
        if let Some(d) = cfg.dim {
            pool.bank.set_dim(d);
        }
        Self {
            pool,
            calib: Calibrator::new(
                l,
                a.calib_window,
                a.calib_label_prior,
                a.calib_pooled_prior,
                a.calib_newton_steps,
                a.calib_min_slope,
            ),
            global: GlobalSums {
                base: 0,
                cells: vec![[0.0; 4]; n * l],
                pos: vec![0.0; l],
                mass: 0.0,
                pairs: vec![[0.0; 4]; n * n.saturating_sub(1) / 2 * l],
                updates: 0,
                unlabelled: if a.unlabelled_ramp == 0.0 {
                    a.unlabelled_weight
                } else {
                    0.0
                },
            },
            cursor: 0,
            em_updates: 0,
            credit: CreditState {
                sum: vec![0.0; n],
                count: vec![0.0; n],
                ..Default::default()
            },
            model_score: Tally::default(),
            vote_score: Tally::default(),
        }
    }

    pub fn pool(&self) -> &Pool {
        &self.pool
    }

    pub fn calibrator(&self) -> &Calibrator {
        &self.calib
    }

    pub fn em_updates(&self) -> u64 {
        self.em_updates
    }

    /// How the model's and majority vote's decisions scored on the labelled rounds.
    pub fn scores(&self) -> (Tally, Tally) {
        (self.model_score, self.vote_score)
    }
}

/// Majority vote of a round: a label is on when MORE than half of the present reporters report
/// it (SPEC §6).
pub fn majority_vote(round: &Round, l: usize) -> Vec<u8> {
    let n = round.present.len();
    let present = round.present.iter().filter(|&&p| p).count();
    (0..l)
        .map(|k| {
            let votes = (0..n)
                .filter(|&i| round.present[i] && round.reports[i * l + k] != 0)
                .count();
            (2 * votes > present) as u8
        })
        .collect()
}

use pool::decay;

impl Engine {
    fn ad(&self) -> &Adaptive {
        self.adaptive
            .as_ref()
            .expect("adaptive state exists under method = adaptive")
    }

    fn ad_mut(&mut self) -> &mut Adaptive {
        self.adaptive
            .as_mut()
            .expect("adaptive state exists under method = adaptive")
    }

    /// The adaptive state, if this engine runs `method = "adaptive"`.
    pub fn adaptive(&self) -> Option<&Adaptive> {
        self.adaptive.as_ref()
    }

    /// The credit state after a round with credits `phi` (all `n` reporters) over
    /// `coalition`: the credit scale `(decayed sum, decayed count)` of the per-round mean
    /// `|phi|`, and per reporter the discounted sum of its scaled credits and its discounted
    /// count of rounds.
    fn credit_state_after(&self, phi: &[f64], coalition: &[usize]) -> CreditState {
        let a = &self.cfg.adaptive;
        let mut st = self.ad().credit.clone();
        if a.credit_half_life > 0.0 {
            let g = decay(1.0, a.credit_half_life);
            let m = if coalition.is_empty() {
                0.0
            } else {
                coalition.iter().map(|&i| phi[i].abs()).sum::<f64>() / coalition.len() as f64
            };
            st.scale_num = g * st.scale_num + m;
            st.scale_den = g * st.scale_den + 1.0;
        }
        let s = st.scale();
        let g = decay(1.0, a.credit_memory);
        for &i in coalition {
            let x = if s > 0.0 { phi[i] / s } else { 0.0 };
            st.sum[i] = g * st.sum[i] + x;
            st.count[i] = g * st.count[i] + 1.0;
        }
        st
    }

    /// The adaptive reputation update (docs/METHOD.md §6): credits divided by the running credit
    /// scale; then either SPEC's multiplicative update or the discounted one (a softmax of each
    /// reporter's recent mean credit, capped); then fixed-share mixing.
    pub(crate) fn ad_reputation(&self, w: &[f64], phi: &[f64], coalition: &[usize]) -> Vec<f64> {
        let a = &self.cfg.adaptive;
        let st = self.credit_state_after(phi, coalition);
        let raw = match a.reputation {
            Reputation::Multiplicative => {
                let s = st.scale();
                let scaled: Vec<f64> = if a.credit_half_life > 0.0 {
                    if s > 0.0 && s.is_finite() {
                        phi.iter().map(|p| p / s).collect()
                    } else {
                        vec![0.0; phi.len()]
                    }
                } else {
                    phi.to_vec()
                };
                crate::engine::reputation_update(w, &scaled, a.eta)
            }
            Reputation::Discounted => {
                let score: Vec<f64> = (0..w.len())
                    .map(|i| {
                        let den = st.count[i] + a.credit_prior_rounds;
                        let m = if den > 0.0 { st.sum[i] / den } else { 0.0 };
                        a.reputation_beta * m.min(a.credit_cap)
                    })
                    .collect();
                let top = score.iter().copied().fold(f64::NEG_INFINITY, f64::max);
                let e: Vec<f64> = score.iter().map(|v| (v - top).exp()).collect();
                let z: f64 = e.iter().sum();
                e.iter().map(|v| v / z).collect()
            }
        };
        let mixed = crate::engine::fixed_share(&raw, a.fixed_share);
        // Under `discounted`, a reporter that sat the round out keeps its weight: absence says
        // nothing about its accuracy, and the softmax would otherwise move it with the others'
        // credit. The coalition shares the rest in the proportions the update gave it.
        // (`multiplicative` is SPEC's update, kept as SPEC has it.)
        let n = w.len();
        if a.reputation != Reputation::Discounted || coalition.len() == n || coalition.is_empty() {
            return mixed;
        }
        let mut present = vec![false; n];
        for &i in coalition {
            present[i] = true;
        }
        let absent: f64 = (0..n).filter(|&i| !present[i]).map(|i| w[i]).sum();
        let share: f64 = coalition.iter().map(|&i| mixed[i]).sum();
        if share <= 0.0 || !share.is_finite() {
            return w.to_vec();
        }
        (0..n)
            .map(|i| {
                if present[i] {
                    mixed[i] * (1.0 - absent) / share
                } else {
                    w[i]
                }
            })
            .collect()
    }

    /// Advances the credit state with a credited round.
    pub(crate) fn ad_credit_push(&mut self, phi: &[f64], present: &[bool]) {
        let coalition: Vec<usize> = (0..present.len()).filter(|&i| present[i]).collect();
        let st = self.credit_state_after(phi, &coalition);
        self.ad_mut().credit = st;
    }

    /// The weight an unlabelled round's soft truth has now (ramped in with the labels).
    pub(crate) fn unlabelled_weight(&self) -> f64 {
        let a = &self.cfg.adaptive;
        if a.unlabelled_ramp == 0.0 || a.unlabelled_weight == 0.0 {
            return a.unlabelled_weight;
        }
        let n = self.labelled as f64;
        a.unlabelled_weight * n / (n + a.unlabelled_ramp)
    }

    /// Weight of pool entry `pos` in the whole-pool sums, relative to the base clock.
    fn global_weight(&self, pos: usize) -> f64 {
        let a = &self.cfg.adaptive;
        let ad = self.ad();
        let u = if ad.pool.is_labelled(pos) {
            1.0
        } else {
            ad.global.unlabelled
        };
        if u == 0.0 {
            return 0.0;
        }
        let c = ad.pool.clock(pos) as f64 - ad.global.base as f64;
        u * decay(-c, a.half_life)
    }

    /// Adds (`sign = 1`) or removes (`-1`) entry `pos` from the whole-pool sums.
    // Reporter, label and pair indices address flat arrays laid out by (i, k): index loops
    // keep that layout visible.
    #[allow(clippy::needless_range_loop)]
    fn global_add(&mut self, pos: usize, sign: f64) {
        let wgt = sign * self.global_weight(pos);
        if wgt == 0.0 {
            return;
        }
        // The label frequency is evidence about the world, not the reporters: undecayed unless
        // `decay_prior`.
        let wpi = if self.cfg.adaptive.decay_prior || self.cfg.adaptive.half_life == 0.0 {
            wgt
        } else if self.ad().pool.is_labelled(pos) {
            sign
        } else {
            sign * self.ad().global.unlabelled
        };
        self.ad_mut().global.updates += 1;
        let (n, l) = (self.reporters.len(), self.ontology.len());
        let ad = self.adaptive.as_mut().expect("adaptive");
        let pool = &ad.pool;
        let g = &mut ad.global;
        let t = pool.soft(pos);
        for i in 0..n {
            if !pool.bank.present(pos, i) {
                continue;
            }
            for k in 0..l {
                let tk = t[k];
                let c = &mut g.cells[i * l + k];
                if pool.bank.report(pos, i, k) != 0 {
                    c[0] += wgt * tk;
                    c[2] += wgt * (1.0 - tk);
                } else {
                    c[1] += wgt * tk;
                    c[3] += wgt * (1.0 - tk);
                }
            }
        }
        for k in 0..l {
            g.pos[k] += wpi * t[k];
        }
        g.mass += wpi;
        if !pool.is_labelled(pos) {
            return;
        }
        // Error co-occurrence of labelled rounds: with y = 1 reporter i errs iff r_i = 0.
        for i in 0..n {
            if !pool.bank.present(pos, i) {
                continue;
            }
            for j in i + 1..n {
                if !pool.bank.present(pos, j) {
                    continue;
                }
                let base = pair_index(n, i, j) * l;
                for k in 0..l {
                    let ri = pool.bank.report(pos, i, k) as usize;
                    let rj = pool.bank.report(pos, j, k) as usize;
                    let (ei, ej) = if t[k] > 0.5 {
                        (1 - ri, 1 - rj)
                    } else {
                        (ri, rj)
                    };
                    g.pairs[base + k][ei + 2 * ej] += wgt;
                }
            }
        }
    }

    /// Recomputes the whole-pool sums from scratch at the current clock (clears the rounding
    /// that incremental updates accumulate, and rebases the decay).
    fn global_rebuild(&mut self) {
        let (n, l) = (self.reporters.len(), self.ontology.len());
        let now = self.labelled;
        let u = self.unlabelled_weight();
        {
            let g = &mut self.ad_mut().global;
            g.base = now;
            g.unlabelled = u;
            g.cells = vec![[0.0; 4]; n * l];
            g.pos = vec![0.0; l];
            g.mass = 0.0;
            g.pairs = vec![[0.0; 4]; n * n.saturating_sub(1) / 2 * l];
        }
        for pos in 0..self.ad().pool.len() {
            self.global_add(pos, 1.0);
        }
        self.ad_mut().global.updates = 0;
    }

    /// Rebuilds the whole-pool sums when the decay factors would leave a comfortable range, or
    /// when the ramped unlabelled weight has moved by more than `UNLABELLED_REBUILD` of itself
    /// since they were built (about 30 rebuilds over the ramp, none once it has settled).
    fn global_maybe_rebase(&mut self) {
        let h = self.cfg.adaptive.half_life;
        let g = &self.ad().global;
        let u = self.unlabelled_weight();
        let moved = (u - g.unlabelled).abs() > UNLABELLED_REBUILD * u.max(g.unlabelled);
        let worn = g.updates > self.ad().pool.len().max(64);
        if moved || worn || (h > 0.0 && (self.labelled - g.base) as f64 > REBASE_HALF_LIVES * h) {
            self.global_rebuild();
        }
    }

    /// Whole-pool estimates at the current clock: `theta+`, `theta-` of reporter `i` and label
    /// `k`, each shrunk toward the cold prior.
    pub fn global_theta(&self, i: usize, k: usize) -> (f64, f64) {
        let a = &self.cfg.adaptive;
        let g = &self.ad().global;
        let s = decay((self.labelled - g.base) as f64, a.half_life);
        let c = g.cells[i * self.ontology.len() + k];
        let m = a.prior_strength;
        let tp = (m * a.prior_tpr + s * c[0]) / (m + s * (c[0] + c[1]));
        let tn = (m * a.prior_fpr + s * c[2]) / (m + s * (c[2] + c[3]));
        (tp, tn)
    }

    pub fn global_pi(&self, k: usize) -> f64 {
        let a = &self.cfg.adaptive;
        let g = &self.ad().global;
        let s = if a.decay_prior {
            decay((self.labelled - g.base) as f64, a.half_life)
        } else {
            1.0
        };
        let m = a.prior_pi_strength;
        (0.5 * m + s * g.pos[k]) / (m + s * g.mass)
    }

    /// The frozen inputs of a round with reports `(present, reports)` whose neighbours in the
    /// pool are `nb` (best first), evaluated at clock `at` (docs/METHOD.md §2–3).
    fn ad_signals(
        &self,
        present: &[bool],
        reports: &[u8],
        nb: &[(usize, f64)],
        at: u64,
    ) -> Signals {
        let cfg = &self.cfg;
        let a = &cfg.adaptive;
        let ad = self.ad();
        let pool = &ad.pool;
        let l = self.ontology.len();
        let n = self.reporters.len();
        let coalition: Vec<usize> = (0..n).filter(|&i| present[i]).collect();
        let p = coalition.len();
        let u = ad.global.unlabelled;
        // Local priors: Beta pseudo-counts (A+, B+, A-, B-) per member and label.
        let mut prior_cells = vec![[0.0f64; 4]; p * l];
        for (m, &i) in coalition.iter().enumerate() {
            for k in 0..l {
                prior_cells[m * l + k] = if a.hierarchical {
                    let (tp, tn) = self.global_theta(i, k);
                    let s = a.local_strength;
                    [s * tp, s * (1.0 - tp), s * tn, s * (1.0 - tn)]
                } else {
                    let s = a.prior_strength;
                    [
                        s * a.prior_tpr,
                        s * (1.0 - a.prior_tpr),
                        s * a.prior_fpr,
                        s * (1.0 - a.prior_fpr),
                    ]
                };
            }
        }
        let pi_prior: Vec<(f64, f64)> = (0..l)
            .map(|k| {
                if a.hierarchical {
                    let g = self.global_pi(k);
                    (a.local_pi_strength * g, a.local_pi_strength * (1.0 - g))
                } else {
                    (cfg.prior_alpha, cfg.prior_beta)
                }
            })
            .collect();
        let mut theta_pos = vec![0.5; p * l];
        let mut theta_neg = vec![0.5; p * l];
        let mut prior = vec![0.5; l];
        if cfg.ablations.no_context {
            // One notion of reliability over the whole pool: the global estimates themselves.
            for (m, &i) in coalition.iter().enumerate() {
                for k in 0..l {
                    let (tp, tn) = self.global_theta(i, k);
                    theta_pos[m * l + k] = tp;
                    theta_neg[m * l + k] = tn;
                }
            }
            for (k, v) in prior.iter_mut().enumerate() {
                *v = self.global_pi(k);
            }
        } else {
            let mut acc = vec![[0.0f64; 4]; p * l];
            let mut pi_mass = 0.0;
            let mut pi_pos = vec![0.0; l];
            let weight = |pos: usize, sim: f64, decayed: bool| -> f64 {
                let mut w = sim.max(0.0).powf(cfg.tau);
                if decayed && a.half_life > 0.0 {
                    let age = (at as f64 - pool.clock(pos) as f64).abs();
                    w *= decay(age, a.half_life);
                }
                if !pool.is_labelled(pos) {
                    w *= u;
                }
                w
            };
            for &(pos, sim) in nb.iter().take(cfg.k) {
                let w = weight(pos, sim, true);
                if w == 0.0 {
                    continue;
                }
                let t = pool.soft(pos);
                for (m, &i) in coalition.iter().enumerate() {
                    if !pool.bank.present(pos, i) {
                        continue;
                    }
                    for k in 0..l {
                        let c = &mut acc[m * l + k];
                        let tk = t[k];
                        if pool.bank.report(pos, i, k) != 0 {
                            c[0] += w * tk;
                            c[2] += w * (1.0 - tk);
                        } else {
                            c[1] += w * tk;
                            c[3] += w * (1.0 - tk);
                        }
                    }
                }
            }
            for &(pos, sim) in nb.iter().take(cfg.k_prior) {
                let w = weight(pos, sim, a.decay_prior);
                if w == 0.0 {
                    continue;
                }
                pi_mass += w;
                let t = pool.soft(pos);
                for (k, v) in pi_pos.iter_mut().enumerate() {
                    *v += w * t[k];
                }
            }
            for (idx, c) in acc.iter().enumerate() {
                let pc = prior_cells[idx];
                let (ap, bp) = (pc[0] + c[0], pc[1] + c[1]);
                let (an, bn) = (pc[2] + c[2], pc[3] + c[3]);
                theta_pos[idx] = ap / (ap + bp);
                theta_neg[idx] = an / (an + bn);
            }
            for k in 0..l {
                let (pa, pb) = pi_prior[k];
                prior[k] = (pa + pi_pos[k]) / (pa + pb + pi_mass);
            }
        }
        let mut rho = vec![0.0; p * p * l];
        if !cfg.ablations.no_guardrail {
            let scale = decay((self.labelled - ad.global.base) as f64, a.half_life);
            for x in 0..p {
                for y in 0..p {
                    if x == y {
                        continue;
                    }
                    for k in 0..l {
                        let (i, j) = (coalition[x], coalition[y]);
                        rho[(x * p + y) * l + k] = match a.guardrail {
                            Guardrail::Window => self.corr.rho(i, j, k, cfg.rho_max),
                            Guardrail::Pool => {
                                // The phi coefficient is symmetric in (i, j): the cell order
                                // of the unordered pair does not matter.
                                let c =
                                    ad.global.pairs[pair_index(n, i, j) * l + k].map(|v| v * scale);
                                let m: f64 = c.iter().sum();
                                smoothed_phi_f64(c, cfg.rho_max) * m / (m + a.corr_shrink)
                            }
                        };
                    }
                }
            }
        }
        let mut rep = Vec::with_capacity(p * l);
        for &i in &coalition {
            rep.extend_from_slice(&reports[i * l..(i + 1) * l]);
        }
        let wmax = self.w.iter().copied().fold(0.0f64, f64::max);
        let w = coalition
            .iter()
            .map(|&i| match a.weights {
                WeightNorm::MaxOne => self.w[i] / wmax,
                WeightNorm::SumOne => self.w[i],
                WeightNorm::MeanOne => n as f64 * self.w[i],
                WeightNorm::Capped => (n as f64 * self.w[i] / a.full_weight_at).min(1.0),
            })
            .collect();
        Signals {
            l,
            coalition,
            theta_pos,
            theta_neg,
            rho,
            prior,
            reports: rep,
            w,
            eps: cfg.eps,
        }
    }

    /// Calibrated posteriors of a round's signals (the raw ones when calibration is off, which
    /// are then SPEC's `q` exactly).
    fn ad_posterior(&self, s: &Signals) -> Vec<f64> {
        if !self.cfg.adaptive.calibration {
            return s.full_posterior();
        }
        let calib = &self.ad().calib;
        let p = s.prior_logit();
        s.evidence()
            .iter()
            .enumerate()
            .map(|(k, &e)| clip(calib.apply(k, e, p[k]), s.eps))
            .collect()
    }

    /// The soft truth an unlabelled round gets from its signals.
    fn ad_soft_truth(&self, s: &Signals, q: Option<&[f64]>) -> Vec<f64> {
        match (self.cfg.adaptive.soft_truth, q) {
            (SoftTruth::Calibrated, Some(q)) => q.to_vec(),
            (SoftTruth::Calibrated, None) => self.ad_posterior(s),
            (SoftTruth::Raw, _) => s
                .fused_logit()
                .iter()
                .map(|&z| clip(sigmoid(z), s.eps))
                .collect(),
            (SoftTruth::Ds, _) => {
                let mut pure = s.clone();
                pure.w.iter_mut().for_each(|w| *w = 1.0);
                pure.rho.iter_mut().for_each(|r| *r = 0.0);
                pure.fused_logit()
                    .iter()
                    .map(|&z| clip(sigmoid(z), s.eps))
                    .collect()
            }
        }
    }

    pub(crate) fn ad_infer(&self, round: &Round) -> Inference {
        let pool = &self.ad().pool;
        let scan = pool.scan(&round.context, self.labelled);
        let nb: Vec<(usize, f64)> = scan.top.iter().map(|n| (n.pos as usize, n.sim)).collect();
        let signals = self.ad_signals(&round.present, &round.reports, &nb, self.labelled);
        let (q, thresholds) = if self.ad_voting() {
            (
                self.vote_posterior(round),
                vec![self.cfg.adaptive.threshold_initial; self.ontology.len()],
            )
        } else {
            (self.ad_posterior(&signals), self.ad_thresholds())
        };
        let pred = q
            .iter()
            .zip(&thresholds)
            .map(|(&p, &t)| (p >= t) as u8)
            .collect();
        Inference {
            signals,
            q,
            thresholds,
            pred,
            w_used: self.w.clone(),
            scan: Some(scan),
        }
    }

    /// Whether the vote fallback is serving majority vote: until the model's decisions, over the
    /// labelled rounds, have made strictly fewer Hamming errors than the vote's AND have a
    /// micro-F1 at least the vote's (so always with no labels, and on a tie).
    pub fn ad_voting(&self) -> bool {
        let ad = self.ad();
        let (m, v) = (&ad.model_score, &ad.vote_score);
        self.cfg.adaptive.vote_fallback && !(m.errors() < v.errors() && m.f1() >= v.f1())
    }

    /// The vote's posterior: `sigmoid(c (yes - no))` over the present reporters, `c =
    /// ln(prior_tpr / prior_fpr)`: every reporter equally reliable, even odds. At the initial
    /// threshold (in `(1/2, sigmoid(c))`) its decisions are majority vote's exactly.
    fn vote_posterior(&self, round: &Round) -> Vec<f64> {
        let a = &self.cfg.adaptive;
        let l = self.ontology.len();
        let yes = (a.prior_tpr / a.prior_fpr).ln();
        let no = -yes;
        (0..l)
            .map(|k| {
                let z: f64 = (0..round.present.len())
                    .filter(|&i| round.present[i])
                    .map(|i| {
                        if round.reports[i * l + k] != 0 {
                            yes
                        } else {
                            no
                        }
                    })
                    .sum();
                clip(sigmoid(z), self.cfg.eps)
            })
            .collect()
    }

    /// The thresholds in force: the fitted ones shrunk toward `threshold_initial` by the labels
    /// behind them, snapped to the grid.
    pub(crate) fn ad_thresholds(&self) -> Vec<f64> {
        let a = &self.cfg.adaptive;
        let fit = self.threshold.thresholds();
        if a.threshold_shrink == 0.0 || (self.labelled as usize) < a.threshold_min_rounds {
            return fit.to_vec();
        }
        let n = self.labelled as f64;
        let f = n / (n + a.threshold_shrink);
        let step = self.cfg.threshold_step;
        fit.iter()
            .map(|&t| {
                let v = a.threshold_initial + (t - a.threshold_initial) * f;
                ((v / step).round() * step).clamp(step, 1.0 - step)
            })
            .collect()
    }

    /// The scan for a round about to join the pool: the one inference made (completed with the
    /// entries that joined since), or a fresh one. Inference's clock is kept: the round was
    /// observed then.
    fn ad_scan(&self, context: &[f64], scan: Option<&Scan>) -> Scan {
        let pool = &self.ad().pool;
        match scan {
            Some(s) if s.pool_len == pool.len() => s.clone(),
            Some(s) if s.pool_len < pool.len() => pool.extend_scan(context, self.labelled, s),
            _ => pool.scan(context, self.labelled),
        }
    }

    /// Re-estimates one unlabelled entry's soft truth from its neighbours (one E-step).
    fn ad_estep(&mut self, pos: usize) {
        let (present, reports, nb, at) = {
            let pool = &self.ad().pool;
            if pool.is_labelled(pos) {
                return;
            }
            let nb: Vec<(usize, f64)> = pool
                .neighbours(pos)
                .iter()
                .map(|e| (e.pos as usize, e.sim))
                .collect();
            (pool.present(pos), pool.reports(pos), nb, pool.clock(pos))
        };
        let s = self.ad_signals(&present, &reports, &nb, at);
        let t = self.ad_soft_truth(&s, None);
        self.global_add(pos, -1.0);
        let ad = self.ad_mut();
        ad.pool.set_soft(pos, &t);
        ad.em_updates += 1;
        self.global_add(pos, 1.0);
    }

    /// The per-event EM work: E-steps of the next `em_chunk` unlabelled entries, cycling through
    /// them in pool order.
    fn ad_em_chunk(&mut self) {
        // Never more E-steps than there are unlabelled entries: a chunk visits each at most once.
        let chunk = self
            .cfg
            .adaptive
            .em_chunk
            .min(self.ad().pool.unlabelled().len());
        for _ in 0..chunk {
            let ad = self.ad();
            let list = ad.pool.unlabelled();
            if list.is_empty() {
                return;
            }
            // The cursor is a pool position: the next unlabelled entry at or after it.
            let i = list.partition_point(|&p| (p as usize) < ad.cursor);
            let pos = list[if i < list.len() { i } else { 0 }] as usize;
            self.ad_estep(pos);
            self.ad_mut().cursor = pos + 1;
        }
    }

    /// Adds an unlabelled round to the pool (adaptive method). Idempotent per `seq`.
    pub(crate) fn ad_observe(
        &mut self,
        seq: u64,
        round: &Round,
        inf: &Inference,
    ) -> Result<(), FusionError> {
        if self.cfg.adaptive.unlabelled_weight == 0.0 || self.ad().pool.position(seq).is_some() {
            return Ok(());
        }
        self.fix_dim(round.context.len())?;
        let scan = self.ad_scan(&round.context, inf.scan.as_ref());
        let soft = self.ad_soft_truth(&inf.signals, Some(&inf.q));
        let clock = self.labelled;
        let ad = self.ad_mut();
        let pos = ad.pool.insert(
            seq,
            &round.context,
            &round.present,
            &round.reports,
            &soft,
            false,
            clock,
            &scan,
        );
        self.global_add(pos, 1.0);
        self.global_maybe_rebase();
        self.ad_em_chunk();
        Ok(())
    }

    /// The pool side of a labelled round (adaptive method): the entry takes its truth (joining
    /// the pool first if it was never observed), its unlabelled neighbours are re-estimated, the
    /// calibration takes in the round's inference-time logits.
    pub(crate) fn ad_apply(&mut self, lr: &LabelledRound, outcome: Option<&FeedbackOutcome>) {
        let l = lr.truth.len();
        let parts = outcome.filter(|o| o.evidence.len() == l && o.prior_logit.len() == l);
        // The model's posteriors for this round, from its inference-time evidence and prior under
        // the current calibration (which has not seen this label yet): what the threshold is
        // fitted on, and what the vote fallback scores. Without them (a rebuild that carries no
        // outcome, or calibration off) the posteriors the round was served.
        let model_q: Vec<f64> = match parts {
            Some(o) if self.cfg.adaptive.calibration => {
                let calib = &self.ad().calib;
                (0..l)
                    .map(|k| {
                        clip(
                            calib.apply(k, o.evidence[k], o.prior_logit[k]),
                            self.cfg.eps,
                        )
                    })
                    .collect()
            }
            _ => lr.q.clone(),
        };
        if self.cfg.adaptive.vote_fallback && parts.is_some() {
            let t = self.ad_thresholds();
            let vote = majority_vote(&lr.round, l);
            let ad = self.ad_mut();
            for k in 0..l {
                let y = lr.truth[k] != 0;
                ad.model_score.add(model_q[k] >= t[k], y);
                ad.vote_score.add(vote[k] != 0, y);
            }
        }
        self.threshold.push(&model_q, &lr.truth);
        let pos = match self.ad().pool.position(lr.seq) {
            Some(pos) => {
                if self.ad().pool.is_labelled(pos) {
                    None
                } else {
                    self.global_add(pos, -1.0);
                    self.ad_mut().pool.set_label(pos, &lr.truth);
                    self.global_add(pos, 1.0);
                    Some(pos)
                }
            }
            None => {
                let scan = self.ad_scan(&lr.round.context, None);
                let soft: Vec<f64> = lr.truth.iter().map(|&v| v as f64).collect();
                let clock = self.labelled;
                let ad = self.ad_mut();
                let pos = ad.pool.insert(
                    lr.seq,
                    &lr.round.context,
                    &lr.round.present,
                    &lr.round.reports,
                    &soft,
                    true,
                    clock,
                    &scan,
                );
                self.global_add(pos, 1.0);
                Some(pos)
            }
        };
        if self.cfg.adaptive.calibration {
            if let Some(o) = parts {
                self.ad_mut()
                    .calib
                    .push(&o.evidence, &o.prior_logit, &lr.truth);
            }
        }
        if let Some(pos) = pos {
            let touched: Vec<usize> = {
                let pool = &self.ad().pool;
                pool.neighbours(pos)
                    .iter()
                    .map(|e| e.pos as usize)
                    .filter(|&p| !pool.is_labelled(p))
                    .take(self.cfg.adaptive.refresh_max)
                    .collect()
            };
            for p in touched {
                self.ad_estep(p);
            }
        }
    }

    /// After the engine's labelled count advanced: rebase the decayed sums if due, and run the
    /// per-event EM chunk.
    pub(crate) fn ad_after_apply(&mut self) {
        self.global_maybe_rebase();
        self.ad_em_chunk();
    }

    /// A full EM pass (`sweeps` E-steps of every unlabelled entry, in pool order), for idle time
    /// and for `eval`. Returns the number of E-steps made. A no-op under `method = "paper"`.
    pub fn em_pass(&mut self, sweeps: usize) -> usize {
        if self.adaptive.is_none() {
            return 0;
        }
        let mut done = 0;
        for _ in 0..sweeps {
            for pos in 0..self.ad().pool.len() {
                if !self.ad().pool.is_labelled(pos) {
                    self.ad_estep(pos);
                    done += 1;
                }
            }
            self.global_rebuild();
        }
        done
    }
}
