//! The switch's `paper` candidate (docs/METHOD.md §3): PAPER-METHOD.md's rule — each reporter's
//! reliability per label from the kernel-weighted labelled neighbours of the round, Beta
//! smoothing, the prior from the same neighbours, the guardrail's correlation window, its own
//! reputations (kept by the paper method's multiplicative update), its thresholds fitted on its
//! posteriors — run on the labelled entries of the `adaptive` pool. It decides as that rule does;
//! the posteriors it serves are calibrated (the paper's raw posteriors are far from it: ECE about
//! 0.2 on the benchmark suite) by a per-label Platt scaling of its raw logit,
//! `sigmoid(a_k z + b_k)` with `a_k > 0`, fitted on its own labelled rounds, and each label's
//! threshold goes through the same map. A monotone map of both sides keeps every decision the
//! rule's own: calibrating the posteriors and fitting the threshold on them instead changed the
//! decisions and lost 6 of 80 points of the suite's held-out part.
//!
//! Why a fourth candidate: where labels are many and the reporters' reliability varies by
//! scene, or where a reporter has drifted, the purely supervised local estimate beats the
//! model's (which also learns from unlabelled rounds' soft truths and shrinks toward the
//! whole-pool reliabilities), and the switch should be able to serve it.
//!
//! Its neighbours come from the latest `paper_window` labelled rounds only (an exact scan of
//! them): its cost per round is bounded at any pool size, and a reporter's behaviour from before
//! a drift ages out. It keeps no context of its own (the pool's bank holds them) and uses the
//! paper method's own code for the signals ([`crate::method::paper::signals`]).

use std::collections::VecDeque;
use std::sync::Mutex;

use super::pool::{FirstPass, Pool};
use super::Calibrator;
use crate::config::FusionConfig;
use crate::corr::CorrWindow;
use crate::engine::{LabelledRound, Round};
use crate::method::Ctx;
use crate::signals::clip;
use crate::threshold::ThresholdFitter;

/// Once its window is full, the candidate's calibration is refitted after every `CALIB_EVERY`-th
/// labelled round (every round before): a refit
/// passes over its whole window, and refitting each round doubled the switch's cost of a
/// labelled round (`vlmfuse bench`); the map moves slowly, and it never changes a decision.
const CALIB_EVERY: usize = 8;

#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
pub struct PaperCandidate {
    /// The guardrail's window of error correlations, as the paper method keeps it.
    corr: CorrWindow,
    /// Thresholds fitted on the candidate's own (calibrated) posteriors of the labelled rounds.
    threshold: ThresholdFitter,
    /// Its own Platt scaling (under `calibration = true`).
    calib: Calibrator,
    /// Sequence numbers of the latest labelled (or partly labelled) rounds, oldest first.
    recent: VecDeque<u64>,
    /// The candidate's own reputations, kept as the paper method keeps its own: uniform at the
    /// start, then PAPER-METHOD.md §5's multiplicative update on the Shapley credit of the
    /// candidate's signals for each labelled round. The engine's reputations (the adaptive
    /// ones, §4) are not the paper method's: run under them the rule trails the paper method
    /// itself on drifting data, and the switch should be able to serve the paper method.
    w: Vec<f64>,
    /// Bumped by every [`PaperCandidate::learn`]: what [`Memo`] entries are valid for. The
    /// cache's key, not state: a copy read back starts at 0 with an empty cache.
    #[serde(skip)]
    version: u64,
    /// The last answer, reused when the same round is asked again with nothing changed in
    /// between (a round served by this candidate is scored on the very answer it got when its
    /// label arrives next): a cache, so not state.
    #[serde(skip)]
    memo: Memo,
    /// The pool scans' f32 first passes of the latest rounds inferred, so that the answer
    /// asked when one of them is labelled reuses its pass (a cache, so not state).
    #[serde(skip)]
    passes: Passes,
    /// The pool positions of `recent` (`None` where the pool lacks the round), kept in step
    /// with it while the pool evicts nothing: a cache, so not state.
    #[serde(skip)]
    positions: Positions,
}

/// `(pool epoch, version, (seq, position) per entry of recent)`; a position not found yet (the
/// round joins the pool after it is learnt, in a replay) is looked up again when used.
#[derive(Debug, Default)]
struct Positions(Mutex<Option<PositionsAt>>);

/// `(pool epoch, version, (seq, position) per entry of recent)`.
type PositionsAt = (u64, u64, VecDeque<(u64, Option<usize>)>);

impl Clone for Positions {
    /// A copy starts empty (a cache).
    fn clone(&self) -> Self {
        Positions::default()
    }
}

/// How many recent rounds' first passes are kept (a round is usually labelled soon after it is
/// inferred, or much later, when its pass is stale anyway).
const PASSES: usize = 4;

/// Recent first passes: the round's context, the pool's epoch then, the pass.
#[derive(Debug, Default)]
struct Passes(Mutex<VecDeque<KeptPass>>);

/// A round's context, the pool's epoch when it was scanned, and the scan's first pass.
type KeptPass = (Vec<f64>, u64, std::sync::Arc<FirstPass>);

impl Clone for Passes {
    /// A copy starts empty (a cache).
    fn clone(&self) -> Self {
        Passes::default()
    }
}

/// The candidate's answer for a round.
#[derive(Debug, Clone, PartialEq)]
pub struct Answer {
    /// Posteriors, calibrated under `calibration = true`, and the thresholds mapped alike.
    pub q: Vec<f64>,
    pub thresholds: Vec<f64>,
    /// The rule's own posteriors and thresholds (what it decides on and is fitted on).
    raw_q: Vec<f64>,
    raw_thresholds: Vec<f64>,
    /// The raw fused logit per label, which the calibration is fitted on.
    logit: Vec<f64>,
    /// The rule's inputs, which the candidate's own reputations are credited on.
    signals: crate::signals::Signals,
}

impl Answer {
    /// The rule's decisions (`q >= t` on the raw posteriors; the calibrated ones agree).
    pub fn decisions(&self) -> Vec<bool> {
        self.raw_q
            .iter()
            .zip(&self.raw_thresholds)
            .map(|(q, t)| q >= t)
            .collect()
    }
}

/// A question: (version, reputations, round).
type Question = (u64, Vec<f64>, Round);

/// The last question and its answer.
#[derive(Debug, Default)]
struct Memo(Mutex<Option<(Question, Answer)>>);

impl Clone for Memo {
    /// A copy starts empty (a cache).
    fn clone(&self) -> Self {
        Memo::default()
    }
}

impl PaperCandidate {
    pub fn new(cfg: &FusionConfig, n: usize, l: usize) -> Self {
        Self {
            corr: CorrWindow::new(n, l, cfg.corr_window),
            threshold: ThresholdFitter::new(cfg, l),
            calib: {
                let a = &cfg.adaptive;
                Calibrator::new(
                    l,
                    a.calib_window,
                    a.calib_label_prior,
                    a.calib_pooled_prior,
                    a.calib_newton_steps,
                    a.calib_min_slope,
                )
                .refit_every(CALIB_EVERY)
            },
            recent: VecDeque::new(),
            w: vec![1.0 / n as f64; n],
            version: 0,
            memo: Memo::default(),
            passes: Passes::default(),
            positions: Positions::default(),
        }
    }

    /// The candidate's posteriors for a round and the thresholds it decides them at. Rounds not
    /// yet labelled are not among the neighbours, so a round being labelled is not its own.
    /// `first`, when given, is the pool scan's f32 first pass for this round (fresh: covering
    /// the whole pool), which the neighbour search reuses.
    pub fn infer(&self, cx: &Ctx, pool: &Pool, round: &Round, first: Option<&FirstPass>) -> Answer {
        let cx = &Ctx { w: &self.w, ..*cx };
        let kept;
        let first = match first {
            Some(f) => Some(f),
            None => {
                kept = self.pass_of(pool, round);
                kept.as_deref()
            }
        };
        let mut memo = self.memo.0.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(((v, w, r), a)) = memo.as_ref() {
            if *v == self.version && w.as_slice() == cx.w && r == round {
                return a.clone();
            }
        }
        let answer = self.compute(cx, pool, round, first);
        *memo = Some(((self.version, cx.w.to_vec(), round.clone()), answer.clone()));
        answer
    }

    /// Keeps a round's first pass for when it is labelled (made while the pool had
    /// `f.approx.len()` entries, at the pool's current epoch).
    pub fn remember_pass(&self, pool: &Pool, round: &Round, f: &std::sync::Arc<FirstPass>) {
        let mut p = self.passes.0.lock().unwrap_or_else(|e| e.into_inner());
        if p.iter().any(|(c, _, _)| *c == round.context) {
            return;
        }
        p.push_back((round.context.clone(), pool.epoch(), f.clone()));
        while p.len() > PASSES {
            p.pop_front();
        }
    }

    /// A kept first pass for `round`, if the pool has not evicted anything since (positions
    /// unchanged; entries added since are not in the pass, and are not neighbours the
    /// candidate searches unless labelled, in which case the search falls back).
    fn pass_of(&self, pool: &Pool, round: &Round) -> Option<std::sync::Arc<FirstPass>> {
        let p = self.passes.0.lock().unwrap_or_else(|e| e.into_inner());
        p.iter()
            .find(|(c, e, _)| *e == pool.epoch() && *c == round.context)
            .map(|(_, _, f)| f.clone())
    }

    /// The pool positions of the labelled window, from the cache when it is current.
    fn positions(&self, pool: &Pool) -> Vec<usize> {
        let mut c = self.positions.0.lock().unwrap_or_else(|e| e.into_inner());
        match c.as_mut() {
            Some((e, v, p)) if *e == pool.epoch() && *v == self.version => p
                .iter_mut()
                .filter_map(|(seq, at)| {
                    if at.is_none() {
                        *at = pool.position(*seq);
                    }
                    *at
                })
                .collect(),
            _ => {
                let p: VecDeque<(u64, Option<usize>)> = self
                    .recent
                    .iter()
                    .map(|&seq| (seq, pool.position(seq)))
                    .collect();
                let out = p.iter().filter_map(|&(_, at)| at).collect();
                *c = Some((pool.epoch(), self.version, p));
                out
            }
        }
    }

    fn compute(&self, cx: &Ctx, pool: &Pool, round: &Round, first: Option<&FirstPass>) -> Answer {
        let cfg = cx.cfg;
        let bank = &pool.bank;
        let m = cfg.k.max(cfg.k_prior);
        let nb = if cfg.ablations.no_context || bank.dim() == 0 || round.context.is_empty() {
            Vec::new()
        } else {
            let pos = self.positions(pool);
            let covered =
                |f: &&FirstPass| f.len() <= bank.len() && pos.iter().all(|&j| j < f.len());
            match first.filter(covered) {
                // The scan's exact cosines: the exact ranking `top_among` would compute.
                Some(FirstPass::Exact(sims)) => bank.select(pos.iter().map(|&j| (j, sims[j])), m),
                Some(FirstPass::Approx {
                    approx,
                    bound,
                    known,
                }) => bank.top_among_known(
                    &round.context,
                    &pos,
                    m,
                    Some((approx, bound)),
                    Some(known),
                ),
                None => bank.top_among(&round.context, &pos, m),
            }
        };
        let signals = crate::method::paper::signals(cx, round, bank, &self.corr, &nb);
        let raw_q = signals.full_posterior();
        let raw_thresholds = self.threshold.thresholds().to_vec();
        let logit: Vec<f64> = raw_q.iter().map(|&p| (p / (1.0 - p)).ln()).collect();
        let (q, thresholds) = if cfg.adaptive.calibration {
            let map = |k: usize, z: f64| self.calib.apply(k, z, 0.0);
            (
                (0..cx.l).map(|k| clip(map(k, logit[k]), cfg.eps)).collect(),
                raw_thresholds
                    .iter()
                    .enumerate()
                    .map(|(k, &t)| clip(map(k, (t / (1.0 - t)).ln()), cfg.eps))
                    .collect(),
            )
        } else {
            (raw_q.clone(), raw_thresholds.clone())
        };
        Answer {
            q,
            thresholds,
            raw_q,
            raw_thresholds,
            logit,
            signals,
        }
    }

    /// A labelled round, after the switch scored `a` (the candidate's answer for it before its
    /// label): the correlation window, the calibration and the threshold fit take it in, and the
    /// round joins the neighbours searched (once: a later feedback on the same round adds only
    /// labels).
    pub fn learn(
        &mut self,
        cx: &Ctx,
        pool: &Pool,
        lr: &LabelledRound,
        a: &Answer,
        known_before: bool,
    ) {
        let r = &lr.round;
        self.version += 1;
        if !cx.cfg.ablations.frozen_reputation {
            let phi = a
                .signals
                .credit(cx.cfg, &lr.truth, lr.seq)
                .by_reporter(&a.signals.coalition, cx.n);
            self.w = crate::reputation::multiplicative(&self.w, &phi, cx.cfg.eta);
        }
        self.corr.push(&r.present, &r.reports, &lr.truth);
        self.threshold.push(&a.raw_q, &lr.truth);
        if cx.cfg.adaptive.calibration {
            self.calib
                .push(&a.logit, &vec![0.0; a.logit.len()], &lr.truth);
        }
        let mut cache = self.positions.0.lock().unwrap_or_else(|e| e.into_inner());
        let current = matches!(cache.as_ref(), Some((e, v, _)) if *e == pool.epoch() && *v + 1 == self.version);
        if !current {
            *cache = None;
        }
        if !known_before {
            self.recent.push_back(lr.seq);
            if let Some((_, _, p)) = cache.as_mut() {
                p.push_back((lr.seq, pool.position(lr.seq)));
            }
            while self.recent.len() > cx.cfg.adaptive.paper_window {
                self.recent.pop_front();
                if let Some((_, _, p)) = cache.as_mut() {
                    p.pop_front();
                }
            }
        }
        if let Some((_, v, _)) = cache.as_mut() {
            *v = self.version;
        }
    }
}
