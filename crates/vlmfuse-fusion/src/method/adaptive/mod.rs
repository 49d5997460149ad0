//! The `adaptive` fusion method (docs/METHOD.md): the paper method's context-aware Dawid–Skene, extended
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
//! pool (as the paper method's inference is over the bank), the E-step of at most `refresh_max + em_chunk`
//! entries.

use std::sync::Arc;

pub mod ann;
pub mod calibrate;
pub mod config;
pub mod ds;
pub mod gate;
pub mod paper;
pub mod pool;
mod rows;

pub use calibrate::Calibrator;
pub use config::{AdaptiveConfig, Guardrail, Reputation, Serve, SoftTruth, WeightNorm};
pub use gate::{CandidateScore, Predictor, Switch, SwitchRule};
pub use pool::{Pool, Scan};

use super::Ctx;
use crate::bank::Bank;
use crate::config::FusionConfig;
use crate::corr::{pair_index, smoothed_phi_f64, smoothed_phi_signed, CorrWindow};
use crate::engine::{FeedbackOutcome, Inference, LabelledRound, Round};
use crate::reputation::{self, CreditMemory};
use crate::signals::{clip, sigmoid, Signals};
use crate::threshold::ThresholdFitter;
use pool::decay;

/// Whole-pool sums behind the hierarchical prior, decayed to a base clock: the decayed weight of
/// an entry observed at clock `c` is `2^((c - base) / h)` here, and `2^(-(now - base) / h)` times
/// that at clock `now`. Rebased (recomputed) when `now - base` exceeds `REBASE_HALF_LIVES`.
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
struct GlobalSums {
    base: u64,
    /// Per reporter and label: `[r t, (1-r) t, r (1-t), (1-r)(1-t)]` weighted sums.
    cells: Vec<[f64; 4]>,
    /// Per label: weighted sum of soft truths.
    pos: Vec<f64>,
    mass: f64,
    /// Per label: the extra weight of partially labelled entries' known labels over the
    /// unlabelled weight `mass` counts them with (all zero without partial feedback).
    mass_known: Vec<f64>,
    /// Per reporter pair and label: counts `[00, 10, 01, 11]` of the error indicators
    /// `(e_i, e_j)` over the labelled entries (the `pool` guardrail).
    pairs: Vec<[f64; 4]>,
    /// Incremental updates since the last rebuild: after as many as the pool has entries, the
    /// sums are rebuilt to clear the rounding that adding and removing accumulates (amortised
    /// O(n L) per update).
    updates: usize,
    /// The unlabelled weight the sums were built with (it ramps with the labels, so the sums
    /// are rebuilt when it has moved; see `maybe_rebase`).
    unlabelled: f64,
}

impl GlobalSums {
    /// The error co-occurrence counts of reporters `i != j` on label `k`, decayed by `scale`
    /// (the guardrail's table).
    fn errors(&self, n: usize, l: usize, i: usize, j: usize, k: usize, scale: f64) -> [f64; 4] {
        // The phi coefficient is symmetric in (i, j): the cell order of the unordered pair does
        // not matter.
        self.pairs[pair_index(n, i, j) * l + k].map(|v| v * scale)
    }

    /// The largest dependence between two reporters' errors on the labelled entries: per pair,
    /// the signed phi coefficient of their error co-occurrence per label, averaged over labels
    /// weighted by their counts (docs/METHOD.md §3, `switch_dependence`).
    fn max_error_dependence(&self, n: usize, l: usize, scale: f64) -> f64 {
        let mut best = 0.0f64;
        for i in 0..n {
            for j in i + 1..n {
                let (mut sum, mut mass) = (0.0, 0.0);
                for k in 0..l {
                    let c = self.errors(n, l, i, j, k, scale);
                    let m: f64 = c.iter().sum();
                    if m > 0.0 {
                        sum += m * smoothed_phi_signed(c);
                        mass += m;
                    }
                }
                if mass > 0.0 {
                    best = best.max(sum / mass);
                }
            }
        }
        best
    }

    fn new(n: usize, l: usize, unlabelled: f64) -> Self {
        Self {
            base: 0,
            cells: vec![[0.0; 4]; n * l],
            pos: vec![0.0; l],
            mass: 0.0,
            mass_known: vec![0.0; l],
            pairs: vec![[0.0; 4]; n * n.saturating_sub(1) / 2 * l],
            updates: 0,
            unlabelled,
        }
    }
}

/// The kernel-weighted cells `[r t, (1-r) t, r (1-t), (1-r)(1-t)]` of every (member, label)
/// of a round's signals, kept as what is cheapest to add up: per member and label the sums over
/// the neighbours it reported the label on, `A = sum w t r` and `B = sum w (1-t) r`; per label
/// the sums over every neighbour, `S+ = sum w t` and `S- = sum w (1-t)` (shared by the members),
/// less, per member, those over the neighbours it was absent from. The cells are then
/// `[A, S+ - A, B, S- - B]` (plus what partly labelled neighbours add directly). A neighbour
/// costs two multiplies and two adds per member and label instead of four each, four labels a
/// step where the processor has AVX2: the E-steps spent most of their time here.
struct Cells {
    l: usize,
    /// `A` and `B` per (member, label).
    a: Vec<f64>,
    b: Vec<f64>,
    /// `S+` and `S-` per label.
    s_pos: Vec<f64>,
    s_neg: Vec<f64>,
    /// Per (member, label): the part of `S+` and `S-` from neighbours the member was absent
    /// from.
    absent_pos: Vec<f64>,
    absent_neg: Vec<f64>,
    /// Per (member, label): terms added to a cell directly (partly labelled neighbours).
    direct: Vec<[f64; 4]>,
}

impl Cells {
    fn new(members: usize, l: usize) -> Self {
        Self {
            l,
            a: vec![0.0; members * l],
            b: vec![0.0; members * l],
            s_pos: vec![0.0; l],
            s_neg: vec![0.0; l],
            absent_pos: vec![0.0; members * l],
            absent_neg: vec![0.0; members * l],
            direct: vec![[0.0; 4]; members * l],
        }
    }

    /// Cell `j` of member `m`, label `k`, for a term added directly.
    #[inline]
    fn at(&mut self, m: usize, j: usize, k: usize) -> &mut f64 {
        &mut self.direct[m * self.l + k][j]
    }

    /// The four cells of member `m`, label `k`.
    fn cell(&self, m: usize, k: usize) -> [f64; 4] {
        let i = m * self.l + k;
        let d = self.direct[i];
        let pos = self.s_pos[k] - self.absent_pos[i];
        let neg = self.s_neg[k] - self.absent_neg[i];
        // A difference of sums can round a little below zero where the true value is zero (a
        // member that reported the label on every neighbour, or was absent from all): floored.
        [
            self.a[i] + d[0],
            (pos - self.a[i]).max(0.0) + d[1],
            self.b[i] + d[2],
            (neg - self.b[i]).max(0.0) + d[3],
        ]
    }

    /// Adds one neighbour for every member of the coalition. The AVX2 path does the same
    /// multiplies and adds (no FMA) four labels at a time, so it gives the same bits (tested).
    #[inline]
    fn add_neighbour(&mut self, nb: &NeighbourRow) {
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("avx2") {
            // SAFETY: the feature this function is compiled for was just detected.
            unsafe { add_neighbour_avx2(self, nb) };
            return;
        }
        add_neighbour_body(self, nb, false);
    }
}

/// What a neighbour adds to a round's [`Cells`]: its soft truths `t` (one per label), its
/// weight `w`, and its presence flags and reports per reporter, for the round's coalition.
struct NeighbourRow<'a> {
    t: &'a [f64],
    w: f64,
    coalition: &'a [usize],
    present: &'a [u8],
    reps: &'a [u8],
}

/// [`Cells::add_neighbour`]: with `wide`, four labels a step through AVX2 (only from
/// `add_neighbour_avx2`), then the rest one at a time.
#[inline(always)]
fn add_neighbour_body(c: &mut Cells, nb: &NeighbourRow, wide: bool) {
    let (l, t, w) = (c.l, nb.t, nb.w);
    let mut from = 0;
    #[cfg(target_arch = "x86_64")]
    if wide {
        // SAFETY: `wide` is set only by `add_neighbour_avx2`, compiled for AVX2 and called
        // where it was detected.
        from = unsafe { add_neighbour_wide(c, nb) };
    }
    for (k, &tk) in t.iter().enumerate().take(l).skip(from) {
        let (pos_w, neg_w) = (w * tk, w * (1.0 - tk));
        c.s_pos[k] += pos_w;
        c.s_neg[k] += neg_w;
        for (m, &i) in nb.coalition.iter().enumerate() {
            let idx = m * l + k;
            if nb.present[i] == 0 {
                c.absent_pos[idx] += pos_w;
                c.absent_neg[idx] += neg_w;
                continue;
            }
            let on = (nb.reps[i * l + k] != 0) as u8 as f64;
            c.a[idx] += pos_w * on;
            c.b[idx] += neg_w * on;
        }
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn add_neighbour_avx2(c: &mut Cells, nb: &NeighbourRow) {
    add_neighbour_body(c, nb, true);
}

/// The full four-label steps of a neighbour for every member; returns where they stopped.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[inline]
unsafe fn add_neighbour_wide(c: &mut Cells, nb: &NeighbourRow) -> usize {
    use std::arch::x86_64::*;
    let l = c.l;
    let NeighbourRow {
        t,
        w,
        coalition,
        present,
        reps,
    } = *nb;
    assert!(t.len() >= l);
    let n = coalition.len() * l;
    assert!(c.a.len() >= n && c.b.len() >= n && c.absent_pos.len() >= n);
    assert!(c.absent_neg.len() >= n && c.s_pos.len() >= l && c.s_neg.len() >= l);
    assert!(coalition
        .iter()
        .all(|&i| i < present.len() && (i + 1) * l <= reps.len()));
    let wv = _mm256_set1_pd(w);
    let one = _mm256_set1_pd(1.0);
    let bit = |v: u8| (v != 0) as u8 as f64;
    let add = |p: *mut f64, v: __m256d| {
        // SAFETY: callers pass pointers to four in-bounds values.
        unsafe { _mm256_storeu_pd(p, _mm256_add_pd(_mm256_loadu_pd(p), v)) }
    };
    let mut k = 0;
    while k + 4 <= l {
        // SAFETY: k + 4 <= l, and every array indexed below holds the lengths asserted above.
        unsafe {
            let tk = _mm256_loadu_pd(t.as_ptr().add(k));
            let pos_w = _mm256_mul_pd(wv, tk);
            let neg_w = _mm256_mul_pd(wv, _mm256_sub_pd(one, tk));
            add(c.s_pos.as_mut_ptr().add(k), pos_w);
            add(c.s_neg.as_mut_ptr().add(k), neg_w);
            for (m, &i) in coalition.iter().enumerate() {
                let idx = m * l + k;
                if present[i] == 0 {
                    add(c.absent_pos.as_mut_ptr().add(idx), pos_w);
                    add(c.absent_neg.as_mut_ptr().add(idx), neg_w);
                    continue;
                }
                let r = reps.as_ptr().add(i * l + k);
                let on = _mm256_set_pd(bit(*r.add(3)), bit(*r.add(2)), bit(*r.add(1)), bit(*r));
                add(c.a.as_mut_ptr().add(idx), _mm256_mul_pd(pos_w, on));
                add(c.b.as_mut_ptr().add(idx), _mm256_mul_pd(neg_w, on));
            }
        }
        k += 4;
    }
    k
}

const REBASE_HALF_LIVES: f64 = 40.0;
const UNLABELLED_REBUILD: f64 = 0.1;

/// The adaptive method's state.
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
pub struct Adaptive {
    pool: Pool,
    calib: Calibrator,
    global: GlobalSums,
    /// Next pool position the per-event EM visits.
    cursor: usize,
    /// The credits the reputation update remembers.
    credit: CreditMemory,
    /// Decisions of the model and of majority vote scored on the labelled rounds (under
    /// `serve = "vote-fallback"` the vote serves until the model has done better on both counts).
    model_score: Tally,
    vote_score: Tally,
    /// The whole-pool Dawid–Skene's sums (kept under `serve = "switch"`).
    ds: ds::GlobalDs,
    /// Which candidate serves under `serve = "switch"`, and their recent losses.
    switch: Switch,
    /// The switch's `paper` candidate (under `serve = "switch"` with `paper_window > 0`).
    paper: Option<paper::PaperCandidate>,
    /// Fitted on the calibrated posteriors, with this method's own cold-start rule.
    threshold: ThresholdFitter,
    /// The paper method's window of error correlations, kept only under `guardrail = "window"`.
    corr: Option<CorrWindow>,
    /// Bumped whenever what the guardrail's correlations are computed from changes (the pair
    /// sums, their base clock, the window): the key of a [`RhoCache`]. Not state (never
    /// saved; any value works after a load, the caches live within one event).
    #[serde(skip)]
    rho_version: u64,
}

/// The guardrail's correlations per coalition, reused across the E-steps of one event: an
/// E-step of an unlabelled entry leaves the pair sums as they were, so the `p (p - 1) L`
/// smoothed phi coefficients of every E-step after the first are the first one's, bit for
/// bit. Keyed by [`Adaptive::rho_version`].
#[derive(Default)]
struct RhoCache {
    version: u64,
    entries: Vec<(Vec<usize>, Vec<f64>)>,
}

impl RhoCache {
    /// The coalition's correlations at `version`: kept ones, or `compute`'s, then kept.
    fn get_or(
        &mut self,
        version: u64,
        coalition: &[usize],
        compute: impl FnOnce() -> Vec<f64>,
    ) -> Vec<f64> {
        if self.version != version {
            self.version = version;
            self.entries.clear();
        }
        if let Some((_, r)) = self.entries.iter().find(|(c, _)| c == coalition) {
            return r.clone();
        }
        let r = compute();
        self.entries.push((coalition.to_vec(), r.clone()));
        r
    }
}

/// True positives, false positives and false negatives of a stream of decisions.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
struct Tally {
    tp: u64,
    fp: u64,
    fneg: u64,
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
    fn errors(&self) -> u64 {
        self.fp + self.fneg
    }

    /// Micro-F1 (1 with no positive at all).
    fn f1(&self) -> f64 {
        let den = 2 * self.tp + self.fp + self.fneg;
        if den == 0 {
            1.0
        } else {
            2.0 * self.tp as f64 / den as f64
        }
    }
}

/// The mean of two candidates' posteriors, at the mean of their thresholds.
fn blend(qa: &[f64], ta: &[f64], qb: &[f64], tb: &[f64]) -> (Vec<f64>, Vec<f64>) {
    let mean = |x: &[f64], y: &[f64]| x.iter().zip(y).map(|(x, y)| 0.5 * (x + y)).collect();
    (mean(qa, qb), mean(ta, tb))
}

/// Majority vote of a round: a label is on when MORE than half of the present reporters report
/// it (PAPER-METHOD.md §6).
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

impl Adaptive {
    pub fn new(cfg: &FusionConfig, n: usize, l: usize) -> Self {
        let a = &cfg.adaptive;
        let rank_half_life = if a.decay_ranking { a.half_life } else { 0.0 };
        // The method's own cold-start rule for the threshold.
        let tcfg = FusionConfig {
            threshold_initial: a.threshold_initial,
            threshold_min_rounds: a.threshold_min_rounds,
            ..cfg.clone()
        };
        Self {
            pool: Pool::new(n, l, cfg.k.max(cfg.k_prior), cfg.tau, rank_half_life)
                .compact(cfg.adaptive.compact_contexts)
                .approximate(
                    cfg.adaptive.ann_min,
                    cfg.adaptive.ann_cells,
                    cfg.adaptive.ann_probe,
                    cfg.adaptive.ann_ef,
                ),
            calib: Calibrator::new(
                l,
                a.calib_window,
                a.calib_label_prior,
                a.calib_pooled_prior,
                a.calib_newton_steps,
                a.calib_min_slope,
            )
            .refit_every(4),
            global: GlobalSums::new(
                n,
                l,
                if a.unlabelled_ramp == 0.0 {
                    a.unlabelled_weight
                } else {
                    0.0
                },
            ),
            cursor: 0,
            credit: CreditMemory::new(n),
            model_score: Tally::default(),
            vote_score: Tally::default(),
            ds: ds::GlobalDs::new(n, l),
            switch: Switch::default(),
            paper: (a.serve == Serve::Switch && a.paper_window > 0)
                .then(|| paper::PaperCandidate::new(cfg, n, l)),
            threshold: ThresholdFitter::new(&tcfg, l),
            corr: (a.guardrail == Guardrail::Window)
                .then(|| CorrWindow::new(n, l, cfg.corr_window)),
            rho_version: 0,
        }
    }

    pub fn set_dim(&mut self, d: usize) {
        self.pool.bank.set_dim(d);
    }

    /// The pool's contexts (its truths are unused: soft truths live in the pool).
    pub fn bank(&self) -> &Bank {
        &self.pool.bank
    }

    pub fn threshold(&self) -> &ThresholdFitter {
        &self.threshold
    }

    /// The adaptive reputation update (docs/METHOD.md §4): credits divided by the running credit
    /// scale; then either the paper method's multiplicative update or the discounted one; then fixed-share
    /// mixing. Under `discounted`, a reporter that sat the round out keeps its weight: absence
    /// says nothing about its accuracy, and the softmax would otherwise move it with the
    /// others' credit. (`multiplicative` is the paper method's update, kept as docs/PAPER-METHOD.md has it.)
    pub fn reputation(&self, cx: &Ctx, w: &[f64], phi: &[f64], coalition: &[usize]) -> Vec<f64> {
        let a = &cx.cfg.adaptive;
        let st = self
            .credit
            .after(phi, coalition, a.credit_half_life, a.credit_memory);
        match a.reputation {
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
                reputation::fixed_share(
                    &reputation::multiplicative(w, &scaled, a.eta),
                    a.fixed_share,
                )
            }
            Reputation::Discounted => {
                let raw = reputation::discounted(
                    &st,
                    a.credit_prior_rounds,
                    a.reputation_beta,
                    a.credit_cap,
                );
                reputation::keep_absent(w, reputation::fixed_share(&raw, a.fixed_share), coalition)
            }
        }
    }

    /// The weight an unlabelled round's soft truth has now (ramped in with the labels).
    fn unlabelled_weight(cx: &Ctx) -> f64 {
        let a = &cx.cfg.adaptive;
        if a.unlabelled_ramp == 0.0 || a.unlabelled_weight == 0.0 {
            return a.unlabelled_weight;
        }
        let n = cx.labelled as f64;
        a.unlabelled_weight * n / (n + a.unlabelled_ramp)
    }

    /// Weight of pool entry `pos` in the whole-pool sums, relative to the base clock.
    fn global_weight(&self, cx: &Ctx, pos: usize) -> f64 {
        let u = if self.pool.is_labelled(pos) {
            1.0
        } else {
            self.global.unlabelled
        };
        if u == 0.0 {
            return 0.0;
        }
        let c = self.pool.clock(pos) as f64 - self.global.base as f64;
        u * decay(-c, cx.cfg.adaptive.half_life)
    }

    /// Adds (`sign = 1`) or removes (`-1`) entry `pos` from the whole-pool sums.
    // Reporter, label and pair indices address flat arrays laid out by (i, k): index loops
    // keep that layout visible.
    #[allow(clippy::needless_range_loop)]
    fn global_add(&mut self, cx: &Ctx, pos: usize, sign: f64) {
        let wgt = sign * self.global_weight(cx, pos);
        if self.pool.is_partial(pos) {
            self.global_add_known(cx, pos, sign, wgt);
        }
        if wgt == 0.0 {
            return;
        }
        let a = &cx.cfg.adaptive;
        // The label frequency is evidence about the world, not the reporters: undecayed unless
        // `decay_prior`.
        let wpi = if a.decay_prior || a.half_life == 0.0 {
            wgt
        } else if self.pool.is_labelled(pos) {
            sign
        } else {
            sign * self.global.unlabelled
        };
        let (n, l) = (cx.n, cx.l);
        let pool = &self.pool;
        let g = &mut self.global;
        g.updates += 1;
        let t = pool.soft(pos);
        let (present, reps) = (pool.present_row(pos), pool.reports_row(pos));
        for i in 0..n {
            if present[i] == 0 {
                continue;
            }
            for k in 0..l {
                let tk = t[k];
                let c = &mut g.cells[i * l + k];
                if reps[i * l + k] != 0 {
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
        self.rho_version += 1;
        // Error co-occurrence of labelled rounds: with y = 1 reporter i errs iff r_i = 0.
        for i in 0..n {
            if present[i] == 0 {
                continue;
            }
            for j in i + 1..n {
                if present[j] == 0 {
                    continue;
                }
                let base = pair_index(n, i, j) * l;
                for k in 0..l {
                    let ri = reps[i * l + k] as usize;
                    let rj = reps[j * l + k] as usize;
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

    /// The known labels of a partially labelled entry weigh as a labelled entry's do: on top of
    /// the unlabelled weight `wgt` that [`Adaptive::global_add`] gives the whole entry, each
    /// known label gets the difference, in its cells, its prior and (as labelled entries do) its
    /// error co-occurrences.
    #[allow(clippy::needless_range_loop)]
    fn global_add_known(&mut self, cx: &Ctx, pos: usize, sign: f64, wgt: f64) {
        let a = &cx.cfg.adaptive;
        let c = self.pool.clock(pos) as f64 - self.global.base as f64;
        let full = sign * decay(-c, a.half_life);
        let extra = full - wgt;
        let (wpi_full, wpi) = if a.decay_prior || a.half_life == 0.0 {
            (full, wgt)
        } else {
            (sign, sign * self.global.unlabelled)
        };
        let extra_pi = wpi_full - wpi;
        self.rho_version += 1;
        let (n, l) = (cx.n, cx.l);
        let pool = &self.pool;
        let g = &mut self.global;
        let t = pool.soft(pos);
        for k in 0..l {
            if !pool.known(pos, k) {
                continue;
            }
            let tk = t[k];
            for i in 0..n {
                if !pool.bank.present(pos, i) {
                    continue;
                }
                let c = &mut g.cells[i * l + k];
                if pool.bank.report(pos, i, k) != 0 {
                    c[0] += extra * tk;
                    c[2] += extra * (1.0 - tk);
                } else {
                    c[1] += extra * tk;
                    c[3] += extra * (1.0 - tk);
                }
            }
            g.pos[k] += extra_pi * tk;
            g.mass_known[k] += extra_pi;
            for i in 0..n {
                if !pool.bank.present(pos, i) {
                    continue;
                }
                for j in i + 1..n {
                    if !pool.bank.present(pos, j) {
                        continue;
                    }
                    let ri = pool.bank.report(pos, i, k) as usize;
                    let rj = pool.bank.report(pos, j, k) as usize;
                    let (ei, ej) = if tk > 0.5 { (1 - ri, 1 - rj) } else { (ri, rj) };
                    g.pairs[pair_index(n, i, j) * l + k][ei + 2 * ej] += full;
                }
            }
        }
    }

    /// Recomputes the whole-pool sums from scratch at the current clock (clears the rounding
    /// that incremental updates accumulate, and rebases the decay).
    fn global_rebuild(&mut self, cx: &Ctx) {
        self.rho_version += 1;
        self.global = GlobalSums {
            base: cx.labelled,
            ..GlobalSums::new(cx.n, cx.l, Self::unlabelled_weight(cx))
        };
        for pos in 0..self.pool.len() {
            self.global_add(cx, pos, 1.0);
        }
        self.global.updates = 0;
    }

    /// Rebuilds the whole-pool sums when the decay factors would leave a comfortable range, or
    /// when the ramped unlabelled weight has moved by more than `UNLABELLED_REBUILD` of itself
    /// since they were built (about 30 rebuilds over the ramp, none once it has settled).
    fn maybe_rebase(&mut self, cx: &Ctx) {
        let h = cx.cfg.adaptive.half_life;
        let g = &self.global;
        let u = Self::unlabelled_weight(cx);
        let moved = (u - g.unlabelled).abs() > UNLABELLED_REBUILD * u.max(g.unlabelled);
        let worn = g.updates > 4 * self.pool.len().max(64);
        if moved || worn || (h > 0.0 && (cx.labelled - g.base) as f64 > REBASE_HALF_LIVES * h) {
            self.global_rebuild(cx);
        }
        if Self::keeps_ds(cx) {
            self.ds.maybe_rebuild(&self.pool);
        }
    }

    /// Whole-pool estimates at the current clock: `theta+`, `theta-` of reporter `i` and label
    /// `k`, each shrunk toward the cold prior.
    fn global_theta(&self, cx: &Ctx, i: usize, k: usize) -> (f64, f64) {
        let a = &cx.cfg.adaptive;
        let g = &self.global;
        let s = decay((cx.labelled - g.base) as f64, a.half_life);
        let c = g.cells[i * cx.l + k];
        let m = a.prior_strength;
        let tp = (m * a.prior_tpr + s * c[0]) / (m + s * (c[0] + c[1]));
        let tn = (m * a.prior_fpr + s * c[2]) / (m + s * (c[2] + c[3]));
        (tp, tn)
    }

    fn global_pi(&self, cx: &Ctx, k: usize) -> f64 {
        let a = &cx.cfg.adaptive;
        let g = &self.global;
        let s = if a.decay_prior {
            decay((cx.labelled - g.base) as f64, a.half_life)
        } else {
            1.0
        };
        let m = a.prior_pi_strength;
        (0.5 * m + s * g.pos[k]) / (m + s * (g.mass + g.mass_known[k]))
    }

    /// The frozen inputs of a round with reports `(present, reports)` whose neighbours in the
    /// pool are `nb` (best first), evaluated at clock `at` (docs/METHOD.md §2–3).
    fn signals(
        &self,
        cx: &Ctx,
        present: &[bool],
        reports: &[u8],
        nb: &[pool::Nb],
        at: u64,
        rho_cache: Option<&mut RhoCache>,
    ) -> Signals {
        let cfg = cx.cfg;
        let a = &cfg.adaptive;
        let pool = &self.pool;
        let (n, l) = (cx.n, cx.l);
        let coalition: Vec<usize> = (0..n).filter(|&i| present[i]).collect();
        let p = coalition.len();
        let u = self.global.unlabelled;
        // Local priors: Beta pseudo-counts (A+, B+, A-, B-) per member and label.
        let mut prior_cells = vec![[0.0f64; 4]; p * l];
        for (m, &i) in coalition.iter().enumerate() {
            for k in 0..l {
                prior_cells[m * l + k] = if a.hierarchical {
                    let (tp, tn) = self.global_theta(cx, i, k);
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
                    let g = self.global_pi(cx, k);
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
                    let (tp, tn) = self.global_theta(cx, i, k);
                    theta_pos[m * l + k] = tp;
                    theta_neg[m * l + k] = tn;
                }
            }
            for (k, v) in prior.iter_mut().enumerate() {
                *v = self.global_pi(cx, k);
            }
        } else {
            // The four cells of every (member, label), one array per cell (see `Cells`).
            let mut acc = Cells::new(p, l);
            let mut pi_mass = 0.0;
            let mut pi_pos = vec![0.0; l];
            // The entry's weight before the unlabelled factor, and after it.
            // Without decay a neighbour's ranking weight is `kernel(sim)` itself, computed
            // when it joined the list: the same expression, so the same bits, without a
            // `powf` per neighbour and E-step.
            let keyed = a.half_life <= 0.0;
            let weight = |e: &pool::Nb, decayed: bool| -> (f64, f64) {
                let (pos, sim) = (e.pos as usize, e.sim);
                debug_assert!(!keyed || e.key == pool::kernel(sim, cfg.tau));
                let mut w = if keyed {
                    e.key
                } else {
                    pool::kernel(sim, cfg.tau)
                };
                if decayed && a.half_life > 0.0 {
                    let age = (at as f64 - pool.clock(pos) as f64).abs();
                    w *= decay(age, a.half_life);
                }
                let full = w;
                if !pool.is_labelled(pos) {
                    w *= u;
                }
                (full, w)
            };
            // Per label: the extra prior mass of partially labelled neighbours' known labels.
            let mut pi_known = vec![0.0; l];
            pool.prefetch(
                nb.iter()
                    .take(cfg.k.max(cfg.k_prior))
                    .map(|n| n.pos as usize),
            );
            for e in nb.iter().take(cfg.k) {
                let pos = e.pos as usize;
                let (full, w) = weight(e, true);
                if pool.is_partial(pos) && full > w {
                    // Known labels of a partly labelled neighbour weigh as labelled ones.
                    let t = pool.soft(pos);
                    let (present, reps) = (pool.present_row(pos), pool.reports_row(pos));
                    for (m, &i) in coalition.iter().enumerate() {
                        if present[i] == 0 {
                            continue;
                        }
                        for k in (0..l).filter(|&k| pool.known(pos, k)) {
                            let x = full - w;
                            let on = reps[i * l + k] != 0;
                            match on {
                                true => {
                                    *acc.at(m, 0, k) += x * t[k];
                                    *acc.at(m, 2, k) += x * (1.0 - t[k]);
                                }
                                false => {
                                    *acc.at(m, 1, k) += x * t[k];
                                    *acc.at(m, 3, k) += x * (1.0 - t[k]);
                                }
                            }
                        }
                    }
                }
                if w == 0.0 {
                    continue;
                }
                // One row holds all of these (`rows.rs`): a neighbour's few cache lines.
                let t = pool.soft(pos);
                let (present, reps) = (pool.present_row(pos), pool.reports_row(pos));
                acc.add_neighbour(&NeighbourRow {
                    t,
                    w,
                    coalition: &coalition,
                    present,
                    reps,
                });
            }
            for e in nb.iter().take(cfg.k_prior) {
                let pos = e.pos as usize;
                let (full, w) = weight(e, a.decay_prior);
                if pool.is_partial(pos) && full > w {
                    let t = pool.soft(pos);
                    for k in (0..l).filter(|&k| pool.known(pos, k)) {
                        pi_known[k] += full - w;
                        pi_pos[k] += (full - w) * t[k];
                    }
                }
                if w == 0.0 {
                    continue;
                }
                pi_mass += w;
                let t = pool.soft(pos);
                for (k, v) in pi_pos.iter_mut().enumerate() {
                    *v += w * t[k];
                }
            }
            for (idx, pc) in prior_cells.iter().enumerate() {
                let c = acc.cell(idx / l, idx % l);
                let (ap, bp) = (pc[0] + c[0], pc[1] + c[1]);
                let (an, bn) = (pc[2] + c[2], pc[3] + c[3]);
                theta_pos[idx] = ap / (ap + bp);
                theta_neg[idx] = an / (an + bn);
            }
            for k in 0..l {
                let (pa, pb) = pi_prior[k];
                prior[k] = (pa + pi_pos[k]) / (pa + pb + (pi_mass + pi_known[k]));
            }
        }
        let rho = match rho_cache {
            Some(c) => c.get_or(self.rho_version, &coalition, || self.rho(cx, &coalition)),
            None => self.rho(cx, &coalition),
        };
        let mut rep = Vec::with_capacity(p * l);
        for &i in &coalition {
            rep.extend_from_slice(&reports[i * l..(i + 1) * l]);
        }
        let wmax = cx.w.iter().copied().fold(0.0f64, f64::max);
        let w = coalition
            .iter()
            .map(|&i| match a.weights {
                WeightNorm::MaxOne => cx.w[i] / wmax,
                WeightNorm::SumOne => cx.w[i],
                WeightNorm::MeanOne => n as f64 * cx.w[i],
                WeightNorm::Capped => (n as f64 * cx.w[i] / a.full_weight_at).min(1.0),
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

    /// The guardrail's correlations for a coalition: `rho[(x p + y) L + k]` for members `x != y`.
    fn rho(&self, cx: &Ctx, coalition: &[usize]) -> Vec<f64> {
        let cfg = cx.cfg;
        let a = &cfg.adaptive;
        let (n, l) = (cx.n, cx.l);
        let p = coalition.len();
        let mut rho = vec![0.0; p * p * l];
        if !cfg.ablations.no_guardrail {
            let scale = decay((cx.labelled - self.global.base) as f64, a.half_life);
            for x in 0..p {
                for y in 0..p {
                    if x == y {
                        continue;
                    }
                    for k in 0..l {
                        let (i, j) = (coalition[x], coalition[y]);
                        rho[(x * p + y) * l + k] = match &self.corr {
                            // `guardrail = "window"`: the paper method's.
                            Some(corr) => corr.rho(i, j, k, cfg.rho_max),
                            None => {
                                let c = self.global.errors(n, l, i, j, k, scale);
                                let m: f64 = c.iter().sum();
                                smoothed_phi_f64(c, cfg.rho_max) * m / (m + a.corr_shrink)
                            }
                        };
                    }
                }
            }
        }
        rho
    }

    /// Calibrated posteriors of a round's signals (the raw ones when calibration is off, which
    /// are then the paper method's `q` exactly).
    fn posterior(&self, cx: &Ctx, s: &Signals) -> Vec<f64> {
        if !cx.cfg.adaptive.calibration {
            return s.full_posterior();
        }
        let p = s.prior_logit();
        s.evidence()
            .iter()
            .enumerate()
            .map(|(k, &e)| clip(self.calib.apply(k, e, p[k]), s.eps))
            .collect()
    }

    /// The soft truth an unlabelled round gets from its signals.
    fn soft_truth(&self, cx: &Ctx, s: &Signals, q: Option<&[f64]>) -> Vec<f64> {
        match (cx.cfg.adaptive.soft_truth, q) {
            (SoftTruth::Calibrated, Some(q)) => q.to_vec(),
            (SoftTruth::Calibrated, None) => self.posterior(cx, s),
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

    /// Infers a round against the pool. `sims`, when given, are the round's similarities to
    /// earlier rounds indexed by `seq` (a batched GEMM's row); else the pool is scanned.
    pub fn infer(&self, cx: &Ctx, round: &Round, sims: Option<&[f64]>) -> Inference {
        let scan = match sims {
            // Precomputed cosines are exact: the approximate index, once in use, decides instead.
            Some(s) if !self.pool.ann_active() => self.pool.scan_by_seq(s, cx.labelled),
            _ => self.pool.scan(&round.context, cx.labelled),
        };
        let signals = self.signals(
            cx,
            &round.present,
            &round.reports,
            &scan.top,
            cx.labelled,
            None,
        );
        let initial = || vec![cx.cfg.adaptive.threshold_initial; cx.l];
        // The scan's f32 first pass, when it covers the pool as it is now.
        let first = scan
            .first_pass
            .as_ref()
            .filter(|_| scan.epoch == self.pool.epoch() && scan.pool_len == self.pool.len());
        if let (Some(p), Some(f)) = (&self.paper, first) {
            p.remember_pass(&self.pool, round, f);
        }
        let first = first.map(|f| f.as_ref());
        let (q, thresholds) = match self.serving(cx) {
            Predictor::MajorityVote => (self.vote_posterior(cx, round), initial()),
            Predictor::DawidSkene => (
                self.ds_params(cx)
                    .posterior(&round.present, &round.reports, cx.cfg.eps),
                initial(),
            ),
            Predictor::Paper | Predictor::Blend => {
                let model = || (self.posterior(cx, &signals), self.thresholds(cx));
                match (&self.paper, self.serving(cx)) {
                    (Some(p), Predictor::Paper) => {
                        let a = p.infer(cx, &self.pool, round, first);
                        (a.q, a.thresholds)
                    }
                    (Some(p), _) => {
                        let a = p.infer(cx, &self.pool, round, first);
                        let (q, t) = model();
                        blend(&q, &t, &a.q, &a.thresholds)
                    }
                    (None, _) => model(),
                }
            }
            Predictor::Model => (self.posterior(cx, &signals), self.thresholds(cx)),
        };
        Inference::decide(signals, q, thresholds, cx.w, Some(scan))
    }

    /// What the switch's `paper` candidate answers for a round (posteriors, thresholds), when
    /// it is kept.
    pub fn paper_candidate(&self, cx: &Ctx, round: &Round) -> Option<(Vec<f64>, Vec<f64>)> {
        self.paper.as_ref().map(|p| {
            let a = p.infer(cx, &self.pool, round, None);
            (a.q, a.thresholds)
        })
    }

    /// The candidates' recent scores that decide who serves: under `switch` all three
    /// (discounted), under `vote-fallback` the model's and the vote's over every labelled round
    /// (the loss is then the error count), under `model` none.
    pub fn candidate_scores(&self, cx: &Ctx) -> Vec<CandidateScore> {
        match cx.cfg.adaptive.serve {
            Serve::Switch => self.switch.scores(self.paper.is_some()),
            Serve::VoteFallback => [
                (Predictor::Model, &self.model_score),
                (Predictor::MajorityVote, &self.vote_score),
            ]
            .into_iter()
            .map(|(p, t)| CandidateScore {
                predictor: p,
                loss: t.errors() as f64,
                errors: t.errors() as f64,
                micro_f1: t.f1(),
            })
            .collect(),
            Serve::Model => Vec::new(),
        }
    }

    /// The predictor that decides the next round (docs/METHOD.md §3).
    pub fn serving(&self, cx: &Ctx) -> Predictor {
        match cx.cfg.adaptive.serve {
            Serve::Switch => self.switch.serving(),
            Serve::Model => Predictor::Model,
            Serve::VoteFallback => {
                // Until the model's decisions, over the labelled rounds, have made strictly
                // fewer Hamming errors than the vote's AND have a micro-F1 at least the vote's
                // (so always with no labels, and on a tie).
                let (m, v) = (&self.model_score, &self.vote_score);
                if m.errors() < v.errors() && m.f1() >= v.f1() {
                    Predictor::Model
                } else {
                    Predictor::MajorityVote
                }
            }
        }
    }

    /// Whether the whole-pool Dawid–Skene is kept (it serves only under `switch`).
    fn keeps_ds(cx: &Ctx) -> bool {
        cx.cfg.adaptive.serve == Serve::Switch
    }

    /// The whole-pool Dawid–Skene as its sums stand.
    fn ds_params(&self, cx: &Ctx) -> ds::DsParams {
        self.ds.params(&cx.cfg.adaptive, cx.cfg.eps)
    }

    /// E-steps of the whole-pool Dawid–Skene for these entries (one set of parameters for the
    /// batch, then the sums follow each entry's new soft truths).
    fn ds_esteps(&mut self, cx: &Ctx, order: &[usize]) {
        if !Self::keeps_ds(cx) || order.is_empty() {
            return;
        }
        let par = self.ds_params(cx);
        let l = cx.l;
        let (mut t, mut old) = (vec![0.0; l], vec![0.0; l]);
        for &pos in order {
            if self.pool.is_labelled(pos) {
                continue;
            }
            par.posterior_into(&self.pool, pos, cx.cfg.eps, &mut t);
            old.copy_from_slice(self.pool.gsoft(pos));
            self.pool.set_gsoft(pos, &t);
            self.ds.replace(&self.pool, pos, &old);
        }
    }

    /// A new pool entry joins the whole-pool Dawid–Skene with its E-step posterior; a full fit
    /// follows when the pool has doubled since the last one.
    fn ds_join(&mut self, cx: &Ctx, pos: usize) {
        if !Self::keeps_ds(cx) {
            return;
        }
        let t = self.ds_params(cx).posterior_of(&self.pool, pos, cx.cfg.eps);
        self.pool.set_gsoft(pos, &t);
        self.ds.add(&self.pool, pos, 1.0);
        self.ds
            .maybe_refit(&mut self.pool, &cx.cfg.adaptive, cx.cfg.eps);
    }

    /// The vote's posterior: `sigmoid(c (yes - no))` over the present reporters, `c =
    /// ln(prior_tpr / prior_fpr)`: every reporter equally reliable, even odds. At the initial
    /// threshold (in `(1/2, sigmoid(c))`) its decisions are majority vote's exactly.
    fn vote_posterior(&self, cx: &Ctx, round: &Round) -> Vec<f64> {
        let a = &cx.cfg.adaptive;
        let l = cx.l;
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
                clip(sigmoid(z), cx.cfg.eps)
            })
            .collect()
    }

    /// The thresholds in force: the fitted ones shrunk toward `threshold_initial` by the labels
    /// behind them, snapped to the grid.
    fn thresholds(&self, cx: &Ctx) -> Vec<f64> {
        let a = &cx.cfg.adaptive;
        let fit = self.threshold.thresholds();
        if a.threshold_shrink == 0.0 || (cx.labelled as usize) < a.threshold_min_rounds {
            return fit.to_vec();
        }
        let n = cx.labelled as f64;
        let f = n / (n + a.threshold_shrink);
        let step = cx.cfg.threshold_step;
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
    fn scan_for(&self, cx: &Ctx, context: &[f64], scan: Option<&Scan>) -> Scan {
        let pool = &self.pool;
        match scan {
            Some(s) if s.epoch != pool.epoch() => pool.scan(context, cx.labelled),
            Some(s) if s.pool_len == pool.len() => s.clone(),
            // Completing a scan with the entries that joined since gives the fresh exact scan
            // (the best of the old best and the newcomers), but not the approximate index's:
            // it may not have found a newcomer, and a replay (which scans afresh) must build
            // the same lists.
            Some(s) if s.pool_len < pool.len() && !pool.ann_active() => {
                pool.extend_scan(context, cx.labelled, s)
            }
            _ => pool.scan(context, cx.labelled),
        }
    }

    /// Re-estimates one unlabelled entry's soft truth from its neighbours (one E-step).
    fn estep(&mut self, cx: &Ctx, pos: usize, rho: &mut RhoCache) {
        let pool = &self.pool;
        if pool.is_labelled(pos) {
            return;
        }
        let (present, reports, at) = (pool.present(pos), pool.reports(pos), pool.clock(pos));
        let s = self.signals(cx, &present, &reports, pool.neighbours(pos), at, Some(rho));
        let mut t = self.soft_truth(cx, &s, None);
        if pool.is_partial(pos) {
            // Only the unknown labels are estimated; the known ones stay the truth.
            for (k, tk) in t.iter_mut().enumerate() {
                if pool.known(pos, k) {
                    *tk = pool.soft(pos)[k];
                }
            }
        }
        self.global_add(cx, pos, -1.0);
        self.pool.set_soft(pos, &t);
        self.global_add(cx, pos, 1.0);
    }

    /// E-steps of these entries, in order. The next entries' lists and their neighbours' rows
    /// are prefetched a few steps ahead (the E-steps of a large pool wait on memory more than
    /// they compute); hints only, so the results are those of the plain loop.
    fn esteps(&mut self, cx: &Ctx, order: &[usize]) {
        // Lists `AHEAD` steps ahead, their neighbours' rows one step later: at a 300,000-round
        // import 2 steps gave 2,001 rounds/s and 3 gave 2,024-2,055 (one run each).
        const AHEAD: usize = 3;
        let mut rho = RhoCache::default();
        let ahead = cx.cfg.k.max(cx.cfg.k_prior);
        let rows_of = |pool: &Pool, p: usize| {
            pool.prefetch(
                pool.neighbours(p)
                    .iter()
                    .take(ahead)
                    .map(|e| e.pos as usize),
            )
        };
        for &p in order.iter().take(AHEAD) {
            self.pool.prefetch_entry(p);
        }
        for &p in order.iter().take(AHEAD - 1) {
            rows_of(&self.pool, p);
        }
        for (i, &pos) in order.iter().enumerate() {
            if let Some(&p) = order.get(i + AHEAD) {
                self.pool.prefetch_entry(p);
            }
            if let Some(&p) = order.get(i + AHEAD - 1) {
                rows_of(&self.pool, p);
            }
            self.estep(cx, pos, &mut rho);
        }
    }

    /// The per-event EM work: E-steps of the next `em_chunk` unlabelled entries, cycling through
    /// them in pool order.
    fn em_chunk(&mut self, cx: &Ctx) {
        // Never more E-steps than there are unlabelled entries: a chunk visits each at most once.
        let chunk = cx.cfg.adaptive.em_chunk.min(self.pool.unlabelled().len());
        // The entries this chunk visits, known in advance (an E-step labels nothing, so the
        // unlabelled list stays as it is): the cursor is a pool position, each entry the next
        // unlabelled one at or after it.
        let list = self.pool.unlabelled();
        let mut order = Vec::with_capacity(chunk);
        let mut cursor = self.cursor;
        for _ in 0..chunk {
            let i = list.partition_point(|&p| (p as usize) < cursor);
            let pos = list[if i < list.len() { i } else { 0 }] as usize;
            order.push(pos);
            cursor = pos + 1;
        }
        self.esteps(cx, &order);
        self.ds_esteps(cx, &order);
        if let Some(&last) = order.last() {
            self.cursor = last + 1;
        }
    }

    pub fn approximate_knn(&self) -> bool {
        self.pool.ann_active()
    }

    /// See [`Pool::recall`].
    pub fn neighbour_recall(&self, contexts: &[Vec<f64>], at: u64) -> (bool, f64) {
        self.pool.recall(contexts, at)
    }

    /// Pool entries: (labelled, unlabelled).
    pub fn pool_sizes(&self) -> (usize, usize) {
        let u = self.pool.unlabelled().len();
        (self.pool.len() - u, u)
    }

    /// Whether observing round `seq` changes anything: semi-supervision is on and the round is
    /// not in the pool yet (observing is idempotent per `seq`).
    pub fn wants(&self, cx: &Ctx, seq: u64) -> bool {
        cx.cfg.adaptive.unlabelled_weight != 0.0 && self.pool.position(seq).is_none()
    }

    /// Adds an unlabelled round to the pool with its soft truth, then runs the EM chunk. Call it
    /// only when [`Adaptive::wants`] the round.
    ///
    /// `next`: the context of the round the caller will infer next, when it knows it (an
    /// import does), and a helper thread. With the approximate index in use, that context's
    /// candidates are then searched on the helper while this round's EM chunk runs (the
    /// E-steps never read the index), and the next scan takes them if nothing changed the
    /// index in between. The results are those without `next`, bit for bit (tested); only the
    /// time differs.
    pub fn observe(
        &mut self,
        cx: &Ctx,
        seq: u64,
        round: &Round,
        inf: &Inference,
        next: Option<(&[f64], &crate::Beside)>,
    ) {
        let scan = self.scan_for(cx, &round.context, inf.scan.as_ref());
        let soft = self.soft_truth(cx, &inf.signals, Some(&inf.q));
        let pos = self.pool.insert(
            seq,
            &round.context,
            &round.present,
            &round.reports,
            &soft,
            false,
            cx.labelled,
            &scan,
        );
        self.global_add(cx, pos, 1.0);
        self.ds_join(cx, pos);
        self.retain(cx);
        self.maybe_rebase(cx);
        match (next, self.pool.take_ann()) {
            (Some((x, beside)), Some(ivf)) => {
                let job = self.pool.ahead_job();
                // The bank's rows go with the index: the EM chunk reads no context.
                let rows = self.pool.bank.take_rows();
                let search = Arc::new(pool::Search::new(job, ivf, rows, x));
                let theirs = Arc::clone(&search);
                let ahead = beside.run(
                    move || theirs.run(),
                    || {
                        self.em_chunk(cx);
                        // Done first: score the cells the helper has not reached.
                        search.help();
                    },
                );
                // The job, with its handle, ended before `run` returned; were it still held,
                // copies would do.
                let (ivf, rows) = match Arc::try_unwrap(search) {
                    Ok(s) => s.into_parts(),
                    Err(shared) => shared.copy_parts(),
                };
                self.pool.bank.put_rows(rows);
                self.pool.put_ann(ivf, Some(ahead));
            }
            (_, ivf) => {
                if let Some(ivf) = ivf {
                    self.pool.put_ann(ivf, None);
                }
                self.em_chunk(cx);
            }
        }
    }

    /// The bounded pool (`pool_max`, docs/METHOD.md §6): every labelled round stays; once the
    /// unlabelled entries exceed the cap by its slack (a sixteenth of it), the oldest
    /// unlabelled ones leave until the cap is met, in one compaction. Which entries leave
    /// depends on the event order alone, so replays stay exact. A round that leaves and is
    /// labelled later joins again as a labelled entry, with a fresh scan.
    fn retain(&mut self, cx: &Ctx) {
        let cap = cx.cfg.adaptive.pool_max;
        let unlabelled = self.pool.unlabelled().len();
        if cap == 0 || unlabelled <= cap + (cap / 16).max(1) {
            return;
        }
        // Partly labelled entries stay, as labelled ones do.
        let out: Vec<usize> = self.pool.unlabelled()[..unlabelled - cap]
            .iter()
            .map(|&p| p as usize)
            .filter(|&p| !self.pool.is_partial(p))
            .collect();
        for &pos in &out {
            self.global_add(cx, pos, -1.0);
            if Self::keeps_ds(cx) {
                self.ds.add(&self.pool, pos, -1.0);
            }
        }
        let mut dead = vec![false; self.pool.len()];
        for &pos in &out {
            dead[pos] = true;
        }
        let cursor = self.cursor.min(dead.len());
        self.cursor = dead[..cursor].iter().filter(|d| !**d).count();
        self.pool.evict(&dead);
    }

    /// A labelled round: the credit memory takes in its credits; the correlation window (if
    /// kept) and the threshold fitter take it in; the vote fallback scores it (before the label
    /// is learned); the entry takes its truth (joining the pool first if it was never observed),
    /// its unlabelled neighbours are re-estimated, and the calibration takes in the round's
    /// inference-time logits. Then, at the advanced clock, the sums are rebased if due and the
    /// EM chunk runs.
    pub fn apply(&mut self, cx: &Ctx, lr: &LabelledRound, outcome: Option<&FeedbackOutcome>) {
        let a = &cx.cfg.adaptive;
        if let Some(o) = outcome {
            let coalition = lr.round.coalition();
            self.credit =
                self.credit
                    .after(&o.phi, &coalition, a.credit_half_life, a.credit_memory);
        }
        if let Some(corr) = self.corr.as_mut() {
            corr.push(&lr.round.present, &lr.round.reports, &lr.truth);
            self.rho_version += 1;
        }
        let l = lr.truth.len();
        let parts = outcome.filter(|o| o.evidence.len() == l && o.prior_logit.len() == l);
        // The model's posteriors for this round, from its inference-time evidence and prior under
        // the current calibration (which has not seen this label yet): what the threshold is
        // fitted on, and what the vote fallback scores. Without them (a rebuild that carries no
        // outcome, or calibration off) the posteriors the round was served.
        let model_q: Vec<f64> = match parts {
            Some(o) if a.calibration => (0..l)
                .map(|k| {
                    clip(
                        self.calib.apply(k, o.evidence[k], o.prior_logit[k]),
                        cx.cfg.eps,
                    )
                })
                .collect(),
            _ => lr.q.clone(),
        };
        // The `paper` candidate's posteriors for this round, before it learns the label: what
        // the switch scores it on and what its threshold is fitted on.
        let known_before = self
            .pool
            .position(lr.seq)
            .is_some_and(|pos| self.pool.is_labelled(pos) || self.pool.is_partial(pos));
        // Under the reputations before this round's credit (those it was inferred under when
        // no other feedback came between).
        let before = Ctx {
            w: outcome.map_or(cx.w, |o| &o.w_before),
            ..*cx
        };
        let paper_q = self
            .paper
            .as_ref()
            .map(|p| p.infer(&before, &self.pool, &lr.round, None));
        if a.serve != Serve::Model && parts.is_some() {
            let t = self.thresholds(cx);
            let vote = majority_vote(&lr.round, l);
            let model: Vec<bool> = (0..l).map(|k| model_q[k] >= t[k]).collect();
            if a.serve == Serve::VoteFallback {
                for k in (0..l).filter(|&k| lr.truth[k] <= 1) {
                    let y = lr.truth[k] != 0;
                    self.model_score.add(model[k], y);
                    self.vote_score.add(vote[k] != 0, y);
                }
            } else {
                // Dawid-Skene as it stands now: it has observed the round (not its label).
                let ds: Vec<bool> = self
                    .ds_params(cx)
                    .posterior(&lr.round.present, &lr.round.reports, cx.cfg.eps)
                    .iter()
                    .map(|&q| q >= a.threshold_initial)
                    .collect();
                let vote: Vec<bool> = vote.iter().map(|&v| v != 0).collect();
                let (paper, mean) = match &paper_q {
                    Some(pa) => {
                        let (q, t) = blend(&model_q, &t, &pa.q, &pa.thresholds);
                        let mean = q.iter().zip(&t).map(|(q, t)| q >= t).collect();
                        (pa.decisions(), mean)
                    }
                    None => (Vec::new(), Vec::new()),
                };
                // Two reporters erring together break the independence Dawid-Skene (which
                // serves until `switch_min_rounds`) reads reliabilities from agreement under.
                let scale = decay((cx.labelled - self.global.base) as f64, a.half_life);
                let global = &self.global;
                let early = || {
                    a.switch_dependence > 0.0
                        && global.max_error_dependence(cx.n, cx.l, scale) > a.switch_dependence
                };
                self.switch.score(
                    &[ds, model, vote, paper, mean],
                    &lr.truth,
                    &SwitchRule {
                        discount: a.switch_discount,
                        fn_cost: a.switch_fn_cost,
                        margin: a.switch_margin,
                        min_rounds: a.switch_min_rounds,
                        mean_edge: a.switch_mean_edge,
                    },
                    early,
                );
            }
        }
        self.threshold.push(&model_q, &lr.truth);
        if let (Some(p), Some(a)) = (self.paper.as_mut(), &paper_q) {
            p.learn(cx, &self.pool, lr, a, known_before);
        }
        let pos = match self.pool.position(lr.seq) {
            // Labels it already had, or new ones (partial feedback), or an override.
            Some(pos) => {
                self.global_add(cx, pos, -1.0);
                if Self::keeps_ds(cx) {
                    self.ds.add(&self.pool, pos, -1.0);
                }
                self.pool.set_known(pos, &lr.truth);
                self.global_add(cx, pos, 1.0);
                if Self::keeps_ds(cx) {
                    self.ds.add(&self.pool, pos, 1.0);
                }
                Some(pos)
            }
            None => {
                let scan = self.scan_for(cx, &lr.round.context, None);
                let full = lr.truth.iter().all(|&v| v <= 1);
                // Labels the feedback leaves unknown start from the posterior the round got.
                let soft: Vec<f64> = lr
                    .truth
                    .iter()
                    .zip(&lr.q)
                    .map(|(&v, &q)| if v <= 1 { v as f64 } else { q })
                    .collect();
                let pos = self.pool.insert(
                    lr.seq,
                    &lr.round.context,
                    &lr.round.present,
                    &lr.round.reports,
                    &soft,
                    full,
                    cx.labelled,
                    &scan,
                );
                if !full {
                    self.pool.set_known(pos, &lr.truth);
                }
                self.global_add(cx, pos, 1.0);
                self.ds_join(cx, pos);
                Some(pos)
            }
        };
        if a.calibration {
            if let Some(o) = parts {
                self.calib.push(&o.evidence, &o.prior_logit, &lr.truth);
            }
        }
        if let Some(pos) = pos {
            let touched: Vec<usize> = self
                .pool
                .neighbours(pos)
                .iter()
                .map(|e| e.pos as usize)
                .filter(|&p| !self.pool.is_labelled(p))
                .take(a.refresh_max)
                .collect();
            self.esteps(cx, &touched);
        }
        // The engine's labelled count advances with this round.
        let after = Ctx {
            labelled: cx.labelled + 1,
            ..*cx
        };
        self.maybe_rebase(&after);
        self.em_chunk(&after);
    }
}

#[cfg(test)]
mod cells_tests {
    use super::{add_neighbour_body, Cells, NeighbourRow};

    #[test]
    fn every_path_of_add_neighbour_gives_the_same_cells_as_the_four_sums() {
        let mut s = 7u64;
        let mut next = || {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (s >> 11) as f64 / (1u64 << 53) as f64
        };
        // Label counts around the four-wide step, the paper's 14 among them.
        for l in [1usize, 3, 4, 5, 8, 14, 17] {
            let members = 3;
            let mut fast = Cells::new(members, l);
            let mut plain = Cells::new(members, l);
            // The sums as the signals first wrote them: four cells per (member, label).
            let mut reference = vec![[0.0f64; 4]; members * l];
            for _ in 0..60 {
                let w = next() * 0.9;
                let t: Vec<f64> = (0..l).map(|_| next()).collect();
                // Member 1 is absent from about half of the neighbours.
                let present: Vec<u8> = vec![1, (next() < 0.5) as u8, 1];
                let reps: Vec<u8> = (0..members * l).map(|_| (next() < 0.4) as u8).collect();
                let coalition = [0usize, 1, 2];
                let nb = NeighbourRow {
                    t: &t,
                    w,
                    coalition: &coalition,
                    present: &present,
                    reps: &reps,
                };
                fast.add_neighbour(&nb);
                add_neighbour_body(&mut plain, &nb, false);
                for m in (0..members).filter(|&m| present[m] != 0) {
                    let r = &reps[m * l..(m + 1) * l];
                    for k in 0..l {
                        let c = &mut reference[m * l + k];
                        let (pos_w, neg_w) = (w * t[k], w * (1.0 - t[k]));
                        if r[k] != 0 {
                            c[0] += pos_w;
                            c[2] += neg_w;
                        } else {
                            c[1] += pos_w;
                            c[3] += neg_w;
                        }
                    }
                }
            }
            for m in 0..members {
                for k in 0..l {
                    let (got, want) = (fast.cell(m, k), reference[m * l + k]);
                    assert_eq!(got.map(f64::to_bits), plain.cell(m, k).map(f64::to_bits));
                    for j in 0..4 {
                        assert!((got[j] - want[j]).abs() <= 1e-13, "L {l} {got:?} {want:?}");
                    }
                }
            }
        }
    }
}
