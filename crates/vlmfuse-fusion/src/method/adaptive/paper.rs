//! The switch's `paper` candidate (docs/METHOD.md §3): PAPER-METHOD.md's rule — each reporter's
//! reliability per label from the kernel-weighted labelled neighbours of the round, Beta
//! smoothing, the prior from the same neighbours, the guardrail's correlation window, the
//! reputations in force — run on the labelled entries of the `adaptive` pool, at thresholds
//! fitted on its own posteriors.
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

use super::pool::Pool;
use crate::config::FusionConfig;
use crate::corr::CorrWindow;
use crate::engine::{LabelledRound, Round};
use crate::method::Ctx;
use crate::threshold::ThresholdFitter;

#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
pub struct PaperCandidate {
    /// The guardrail's window of error correlations, as the paper method keeps it.
    corr: CorrWindow,
    /// Thresholds fitted on the candidate's own posteriors of the labelled rounds.
    threshold: ThresholdFitter,
    /// Sequence numbers of the latest labelled (or partly labelled) rounds, oldest first.
    recent: VecDeque<u64>,
    /// Bumped by every [`PaperCandidate::learn`]: what [`Memo`] entries are valid for.
    #[serde(default)]
    version: u64,
    /// The last answer, reused when the same round is asked again with nothing changed in
    /// between (a round served by this candidate is scored on the very answer it got when its
    /// label arrives next): a cache, so not state.
    #[serde(skip)]
    memo: Memo,
}

type Answer = (Vec<f64>, Vec<f64>);

/// The last question and answer: (version, reputations, round) -> answer.
#[derive(Debug, Default)]
struct Memo(Mutex<Option<(u64, Vec<f64>, Round, Answer)>>);

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
            recent: VecDeque::new(),
            version: 0,
            memo: Memo::default(),
        }
    }

    /// The candidate's posteriors for a round and the thresholds it decides them at. Rounds not
    /// yet labelled are not among the neighbours, so a round being labelled is not its own.
    pub fn infer(&self, cx: &Ctx, pool: &Pool, round: &Round) -> Answer {
        let mut memo = self.memo.0.lock().unwrap_or_else(|e| e.into_inner());
        if let Some((v, w, r, a)) = memo.as_ref() {
            if *v == self.version && w.as_slice() == cx.w && r == round {
                return a.clone();
            }
        }
        let answer = self.compute(cx, pool, round);
        *memo = Some((self.version, cx.w.to_vec(), round.clone(), answer.clone()));
        answer
    }

    fn compute(&self, cx: &Ctx, pool: &Pool, round: &Round) -> Answer {
        let cfg = cx.cfg;
        let bank = &pool.bank;
        let m = cfg.k.max(cfg.k_prior);
        let nb = if cfg.ablations.no_context || bank.dim() == 0 || round.context.is_empty() {
            Vec::new()
        } else {
            let items = self
                .recent
                .iter()
                .filter_map(|&seq| pool.position(seq))
                .map(|pos| (pos, bank.sim(&round.context, pos)));
            bank.select(items, m)
        };
        let signals = crate::method::paper::signals(cx, round, bank, &self.corr, &nb);
        (
            signals.full_posterior(),
            self.threshold.thresholds().to_vec(),
        )
    }

    /// A labelled round, after the switch scored `q` (the candidate's posteriors for it before
    /// its label): the correlation window and the threshold fit take it in, and the round joins
    /// the neighbours searched (once: a later feedback on the same round adds only labels).
    pub fn learn(&mut self, cx: &Ctx, lr: &LabelledRound, q: &[f64], known_before: bool) {
        let r = &lr.round;
        self.version += 1;
        self.corr.push(&r.present, &r.reports, &lr.truth);
        self.threshold.push(q, &lr.truth);
        if !known_before {
            self.recent.push_back(lr.seq);
            while self.recent.len() > cx.cfg.adaptive.paper_window {
                self.recent.pop_front();
            }
        }
    }
}
