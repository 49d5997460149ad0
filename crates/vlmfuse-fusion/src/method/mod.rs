//! The fusion methods. The engine keeps what every method shares (ontology, reporters,
//! reputations, statistics, the labelled-round counter) and hands each call to its method with a
//! read-only view of that state ([`Ctx`]); each method owns the rest of its state, and none reads
//! another's.
//!
//! - [`paper::Paper`]: docs/PAPER-METHOD.md §1–7 exactly (labelled bank, correlation window, threshold fit).
//! - [`adaptive::Adaptive`]: docs/METHOD.md (pool of every observed round with soft truths,
//!   calibration, vote fallback, drift-aware reputations).

pub mod adaptive;
pub mod paper;

use crate::bank::Bank;
use crate::config::FusionConfig;
use crate::engine::{FeedbackOutcome, Inference, LabelledRound, Round};
use crate::signals::Signals;
use crate::threshold::ThresholdFitter;
use adaptive::Adaptive;
use paper::Paper;

/// The engine's shared state as a method sees it.
#[derive(Clone, Copy)]
pub struct Ctx<'a> {
    pub cfg: &'a FusionConfig,
    /// Configured reporters.
    pub n: usize,
    /// Labels in the ontology.
    pub l: usize,
    /// The reputations in force.
    pub w: &'a [f64],
    /// Labelled rounds applied so far (the engine's clock).
    pub labelled: u64,
}

/// The method an engine runs, with its state.
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
pub enum MethodState {
    Paper(Box<Paper>),
    Adaptive(Box<Adaptive>),
}

impl MethodState {
    pub fn new(cfg: &FusionConfig, n: usize, l: usize) -> Self {
        match cfg.method {
            crate::Method::Paper => MethodState::Paper(Box::new(Paper::new(cfg, n, l))),
            crate::Method::Adaptive => MethodState::Adaptive(Box::new(Adaptive::new(cfg, n, l))),
        }
    }

    /// Fixes the context dimension of the method's bank.
    pub fn set_dim(&mut self, d: usize) {
        match self {
            MethodState::Paper(p) => p.set_dim(d),
            MethodState::Adaptive(a) => a.set_dim(d),
        }
    }

    /// The contexts the method searches: the paper method's labelled bank, or the adaptive pool.
    pub fn bank(&self) -> &Bank {
        match self {
            MethodState::Paper(p) => p.bank(),
            MethodState::Adaptive(a) => a.bank(),
        }
    }

    pub fn threshold(&self) -> &ThresholdFitter {
        match self {
            MethodState::Paper(p) => p.threshold(),
            MethodState::Adaptive(a) => a.threshold(),
        }
    }

    /// `adaptive`'s candidates' recent scores that decide who serves. `None` under `paper`.
    pub fn candidate_scores(&self, cx: &Ctx) -> Option<Vec<adaptive::CandidateScore>> {
        match self {
            MethodState::Paper(_) => None,
            MethodState::Adaptive(a) => Some(a.candidate_scores(cx)),
        }
    }

    /// `adaptive`'s `paper` candidate's answer for a round (posteriors, thresholds).
    pub fn paper_candidate(&self, cx: &Ctx, round: &Round) -> Option<(Vec<f64>, Vec<f64>)> {
        match self {
            MethodState::Paper(_) => None,
            MethodState::Adaptive(a) => a.paper_candidate(cx, round),
        }
    }

    /// The predictor deciding the next round under `adaptive`; `None` under `paper` (whose one
    /// predictor is the method itself).
    pub fn serving(&self, cx: &Ctx) -> Option<adaptive::Predictor> {
        match self {
            MethodState::Paper(_) => None,
            MethodState::Adaptive(a) => Some(a.serving(cx)),
        }
    }

    /// `adaptive`'s pool: (labelled, unlabelled) entries. `None` under `paper`.
    pub fn pool_sizes(&self) -> Option<(usize, usize)> {
        match self {
            MethodState::Paper(_) => None,
            MethodState::Adaptive(a) => Some(a.pool_sizes()),
        }
    }

    pub fn approximate_knn(&self) -> bool {
        match self {
            MethodState::Paper(_) => false,
            MethodState::Adaptive(a) => a.approximate_knn(),
        }
    }

    pub fn neighbour_recall(&self, contexts: &[Vec<f64>], at: u64) -> Option<(bool, f64)> {
        match self {
            MethodState::Paper(_) => None,
            MethodState::Adaptive(a) => Some(a.neighbour_recall(contexts, at)),
        }
    }

    /// Whether unlabelled rounds change the state ([`MethodState::observe`] is not a no-op).
    pub fn observes(&self) -> bool {
        matches!(self, MethodState::Adaptive(_))
    }

    pub fn infer(&self, cx: &Ctx, round: &Round, sims: Option<&[f64]>) -> Inference {
        match self {
            MethodState::Paper(p) => p.infer(cx, round, sims),
            MethodState::Adaptive(a) => a.infer(cx, round, sims),
        }
    }

    /// Whether observing round `seq` changes anything (the engine fixes the dimension first).
    pub fn wants(&self, cx: &Ctx, seq: u64) -> bool {
        match self {
            MethodState::Paper(_) => false,
            MethodState::Adaptive(a) => a.wants(cx, seq),
        }
    }

    pub fn observe(
        &mut self,
        cx: &Ctx,
        seq: u64,
        round: &Round,
        inf: &Inference,
        next: Option<(&[f64], &crate::Beside)>,
    ) {
        match self {
            MethodState::Paper(_) => {}
            MethodState::Adaptive(a) => a.observe(cx, seq, round, inf, next),
        }
    }

    /// The reputations after a credited round (`w` the ones before, `phi` per reporter).
    pub fn reputation(&self, cx: &Ctx, w: &[f64], phi: &[f64], coalition: &[usize]) -> Vec<f64> {
        match self {
            MethodState::Paper(_) => crate::reputation::multiplicative(w, phi, cx.cfg.eta),
            MethodState::Adaptive(a) => a.reputation(cx, w, phi, coalition),
        }
    }

    /// What the method's calibration is fitted on, kept in the outcome: the round's evidence and
    /// prior log-odds per label under `adaptive`, nothing under `paper`.
    pub fn calibration_inputs(&self, s: &Signals) -> (Vec<f64>, Vec<f64>) {
        match self {
            MethodState::Paper(_) => (Vec::new(), Vec::new()),
            MethodState::Adaptive(_) => (s.evidence(), s.prior_logit()),
        }
    }

    /// The method's side of a labelled round. `cx.w` are the reputations after its outcome and
    /// `cx.labelled` the count before it (the engine advances it after this returns).
    pub fn apply(&mut self, cx: &Ctx, lr: &LabelledRound, outcome: Option<&FeedbackOutcome>) {
        match self {
            MethodState::Paper(p) => p.apply(lr),
            MethodState::Adaptive(a) => a.apply(cx, lr, outcome),
        }
    }
}
