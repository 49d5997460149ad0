//! The one replay: an engine's events in, the engine they lead to out. Two kinds of event make
//! an engine's history, in the order its writer saw them: a round was fused and stored
//! ([`Replay::round`]: inferred, unless the inference it was served is given, then observed),
//! and a round got its feedback ([`Replay::feedback`]: credited, unless the outcome computed
//! then is given, then applied). The store rebuilds the service's engine with it on start
//! (stored inferences and outcomes, or fresh ones when the configured method changed), and
//! `eval` runs the paper's protocol with it.
//!
//! The protocol (PAPER-METHOD.md §9, `eval`, [`replay()`]): rounds in file order, each first predicted with
//! the state as it stands and then learned from if it has truth. The first `split` share is
//! history and is not scored. With `batch_knn`, the similarities of a block of upcoming rounds to
//! every earlier round are one GEMM (faer) instead of one dot product per pair; each round then
//! reads, from its row, the entries its method's bank holds at that moment, so the results are
//! those of the per-query path up to the GEMM's rounding.

use crate::config::{FusionConfig, Method};
use crate::engine::{Engine, FeedbackOutcome, Inference, LabelledRound, Round, RoundRecord};
use crate::error::FusionError;
use crate::method::adaptive::majority_vote;
use crate::metrics::{MetricsAcc, Scores};
use crate::ontology::Ontology;
use crate::signals::ShapleyMethod;
use faer::{Accum, MatMut, MatRef, Par};
use std::collections::{BTreeSet, HashMap};
use std::time::Instant;

/// A replay that cannot go on: the engine refused an event, or the events contradict each other
/// or the engine (a damaged or foreign history).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ReplayError {
    #[error(transparent)]
    Fusion(#[from] FusionError),
    #[error("{0}")]
    Inconsistent(String),
}

/// A round was fused and stored.
#[derive(Debug, Clone)]
pub struct RoundEvent<'a> {
    pub seq: u64,
    pub round: Round,
    /// The inference the round was served; `None`: infer it now, against the state as it stands.
    pub served: Option<Inference>,
    /// For a fresh inference: the round's cosines to earlier rounds, indexed by `seq`
    /// ([`Engine::infer_with_sims`]); `None`: the method searches its bank itself.
    pub sims: Option<&'a [f64]>,
    /// Whether the round joins the state ([`Engine::observe`]); `eval --frozen`'s test rounds
    /// are only predicted.
    pub observe: bool,
    /// A [`FeedbackEvent`] for this round without a stored outcome follows: keep the inference
    /// until then, its credit is computed from it.
    pub credit_later: bool,
}

/// A round got its feedback.
#[derive(Debug, Clone)]
pub struct FeedbackEvent {
    pub seq: u64,
    pub truth: Vec<u8>,
    /// What was stored with it; `None`: the round's [`RoundEvent`] (with `credit_later`) came
    /// earlier in this replay, and the credit is computed now from the inference it got.
    pub stored: Option<StoredLabel>,
    /// Another feedback on this round follows (partial feedback comes in parts): without a
    /// stored outcome its credit needs the round's inference too, so the replay keeps it.
    pub more: bool,
}

/// A feedback as stored: the round, the posteriors it was served and the outcome computed then.
#[derive(Debug, Clone)]
pub struct StoredLabel {
    pub round: Round,
    pub q: Vec<f64>,
    pub outcome: FeedbackOutcome,
}

/// Feeds events to an engine, in order. Given the stored inferences and outcomes the result is
/// the engine that lived through them, bit for bit: the very floating-point operations in the
/// same order.
pub struct Replay<'e> {
    engine: &'e mut Engine,
    /// Fresh inferences of rounds whose feedback (to be credited from them) is still to come.
    pending: HashMap<u64, (Round, Inference)>,
}

impl<'e> Replay<'e> {
    pub fn new(engine: &'e mut Engine) -> Self {
        Self {
            engine,
            pending: HashMap::new(),
        }
    }

    /// The engine as the events so far left it.
    pub fn engine(&self) -> &Engine {
        self.engine
    }

    fn check_round(&self, seq: u64, round: &Round) -> Result<(), ReplayError> {
        if self.engine.fits(round) {
            return Ok(());
        }
        Err(ReplayError::Inconsistent(format!(
            "round {seq} has sizes that do not match {} reporters and {} labels",
            self.engine.reporters().len(),
            self.engine.ontology().len()
        )))
    }

    /// A round was stored: its inference (the one it was served, or a fresh one), then
    /// [`Engine::observe`]. Returns the inference.
    pub fn round(&mut self, ev: RoundEvent<'_>) -> Result<Inference, ReplayError> {
        self.check_round(ev.seq, &ev.round)?;
        let inf = match ev.served {
            Some(inf) => inf,
            None => match ev.sims {
                Some(s) => self.engine.infer_with_sims(&ev.round, s),
                None => self.engine.infer(&ev.round),
            },
        };
        if ev.observe {
            self.engine.observe(ev.seq, &ev.round, &inf)?;
        }
        if ev.credit_later {
            // Credit needs the signals and the reputations used, `apply` the posteriors; the
            // pool scan is spent once the round has been observed.
            let mut kept = inf.clone();
            kept.scan = None;
            self.pending.insert(ev.seq, (ev.round, kept));
        }
        Ok(inf)
    }

    /// A round got its feedback: the outcome (the stored one, or credited now from the round's
    /// inference against the reputations as they stand), then [`Engine::apply`]. Returns the
    /// outcome.
    pub fn feedback(&mut self, ev: FeedbackEvent) -> Result<FeedbackOutcome, ReplayError> {
        let seq = ev.seq;
        let l = self.engine.ontology().len();
        if ev.truth.len() != l {
            return Err(ReplayError::Inconsistent(format!(
                "feedback for round {seq} has {} labels, not {l}",
                ev.truth.len()
            )));
        }
        let (lr, outcome) = match ev.stored {
            Some(s) => {
                self.check_round(seq, &s.round)?;
                if s.q.len() != l {
                    return Err(ReplayError::Inconsistent(format!(
                        "round {seq} has {} posteriors, not {l}",
                        s.q.len()
                    )));
                }
                let lr = LabelledRound {
                    seq,
                    round: s.round,
                    truth: ev.truth,
                    q: s.q,
                };
                (lr, s.outcome)
            }
            None => {
                let kept = if ev.more {
                    self.pending.get(&seq).cloned()
                } else {
                    self.pending.remove(&seq)
                };
                let (round, inf) = kept.ok_or_else(|| {
                    ReplayError::Inconsistent(format!(
                        "feedback for round {seq} precedes the round in event order"
                    ))
                })?;
                let o = self
                    .engine
                    .credit(&inf.signals, &inf.w_used, &ev.truth, seq);
                let lr = LabelledRound {
                    seq,
                    round,
                    truth: ev.truth,
                    q: inf.q,
                };
                (lr, o)
            }
        };
        self.engine.apply(&lr, Some(&outcome))?;
        Ok(outcome)
    }
}

/// A validated line of a rounds file.
#[derive(Debug, Clone)]
pub struct ParsedRound {
    /// 1-based line number in the file, for error messages.
    pub line: usize,
    pub id: String,
    pub round: Round,
    pub truth: Option<Vec<u8>>,
}

/// A rounds-file problem, naming its line.
#[derive(Debug, Clone, thiserror::Error)]
#[error("line {line}: {message}")]
pub struct LineError {
    pub line: usize,
    pub message: String,
}

/// Every reporter name that appears in the records, sorted (PAPER-METHOD.md §9).
pub fn reporters_of(records: &[(usize, RoundRecord)]) -> Result<Vec<String>, LineError> {
    let mut names = BTreeSet::new();
    for (line, r) in records {
        for name in r.reports.keys() {
            if name.trim().is_empty() {
                return Err(LineError {
                    line: *line,
                    message: "a reporter has an empty name".into(),
                });
            }
            names.insert(name.clone());
        }
    }
    Ok(names.into_iter().collect())
}

/// Builds an engine for the file's reporters and validates every record against it. The context
/// dimension is fixed by the config or by the first record, so a later record of another
/// dimension is refused with its line number.
pub fn prepare(
    cfg: &FusionConfig,
    ontology: &Ontology,
    records: &[(usize, RoundRecord)],
) -> Result<(Engine, Vec<ParsedRound>), LineError> {
    let reporters = reporters_of(records)?;
    let first_line = records.first().map(|r| r.0).unwrap_or(1);
    if reporters.is_empty() {
        return Err(LineError {
            line: first_line,
            message: "no reporter appears in the file".into(),
        });
    }
    let mut engine =
        Engine::new(cfg.clone(), ontology.clone(), reporters).map_err(|e| LineError {
            line: first_line,
            message: e.to_string(),
        })?;
    let mut out = Vec::with_capacity(records.len());
    for (line, rec) in records {
        let err = |e: FusionError| LineError {
            line: *line,
            message: e.to_string(),
        };
        if engine.dim().is_none() && !rec.context.is_empty() {
            engine.fix_dim(rec.context.len()).map_err(err)?;
        }
        let (round, truth) = engine.parse(rec).map_err(err)?;
        out.push(ParsedRound {
            line: *line,
            id: rec.id.clone().unwrap_or_else(|| format!("line-{line}")),
            round,
            truth,
        });
    }
    Ok((engine, out))
}

#[derive(Debug, Clone, Copy)]
pub struct ReplayOptions {
    /// Share of rounds (from the start) that is history and not scored.
    pub split: f64,
    /// Stop learning once the history is over.
    pub frozen: bool,
    /// Batch the similarity computation with a GEMM.
    pub batch_knn: bool,
}

impl Default for ReplayOptions {
    fn default() -> Self {
        Self {
            split: 0.7,
            frozen: false,
            batch_knn: true,
        }
    }
}

/// Number of history rounds: `floor(split * N)` (with a hair of slack so 0.7 * 2000 is 1400).
pub fn history_len(n: usize, split: f64) -> usize {
    ((split * n as f64) + 1e-9).floor().clamp(0.0, n as f64) as usize
}

#[derive(Debug, Clone, PartialEq)]
pub struct RoundOutcome {
    pub id: String,
    pub history: bool,
    pub q: Vec<f64>,
    pub thresholds: Vec<f64>,
    pub pred: Vec<u8>,
    pub w_used: Vec<f64>,
    /// Credit per reporter when the round was learned from, else `None`.
    pub phi: Option<Vec<f64>>,
    pub shapley_std_error: Option<Vec<f64>>,
    pub w_after: Vec<f64>,
    /// Seconds of fusion work for this round (inference, credit and update).
    pub latency_s: f64,
}

/// Replays the rounds through the engine (the protocol above). `progress` is called with the
/// number of rounds done.
pub fn replay(
    mut engine: Engine,
    rounds: &[ParsedRound],
    opts: &ReplayOptions,
    progress: &mut dyn FnMut(usize),
) -> Result<(Engine, Vec<RoundOutcome>), ReplayError> {
    let n = rounds.len();
    let n_hist = history_len(n, opts.split);
    let mut out = Vec::with_capacity(n);
    let block = (16_000_000 / n.max(1)).clamp(16, 512);
    let dim = rounds.first().map(|r| r.round.context.len()).unwrap_or(0);
    let batch = opts.batch_knn && BATCHED.contains(&engine.method());
    let mut keys: Vec<f64> = Vec::new();
    if batch {
        keys.reserve(n * dim);
        for r in rounds {
            keys.extend_from_slice(&r.round.context);
        }
    }
    let mut gram: Vec<f64> = Vec::new();
    let mut replay = Replay::new(&mut engine);
    let mut t0 = 0;
    while t0 < n {
        let t1 = (t0 + block).min(n);
        let mut gemm_s = 0.0;
        if batch {
            let start = Instant::now();
            gram.clear();
            gram.resize((t1 - t0) * t1, 0.0);
            let lhs = MatRef::from_row_major_slice(&keys[t0 * dim..t1 * dim], t1 - t0, dim);
            let rhs = MatRef::from_row_major_slice(&keys[..t1 * dim], t1, dim);
            let dst = MatMut::from_row_major_slice_mut(&mut gram, t1 - t0, t1);
            faer::linalg::matmul::matmul(dst, Accum::Replace, lhs, rhs.transpose(), 1.0, Par::Seq);
            gemm_s = start.elapsed().as_secs_f64() / (t1 - t0) as f64;
        }
        for t in t0..t1 {
            let pr = &rounds[t];
            let seq = t as u64;
            let start = Instant::now();
            let history = t < n_hist;
            let learning = history || !opts.frozen;
            let learn = learning && pr.truth.is_some();
            // Row t of the block: cosines to every round of the file before this one, by index.
            let row = (t - t0) * t1;
            let inf = replay.round(RoundEvent {
                seq,
                round: pr.round.clone(),
                served: None,
                sims: batch.then(|| &gram[row..row + t]),
                // As the service does when it stores a round: under `adaptive` it joins the
                // pool (its label, if any, follows right after); under `paper` a no-op.
                observe: learning,
                credit_later: learn,
            })?;
            let mut phi = None;
            let mut std_error = None;
            if let (true, Some(truth)) = (learn, &pr.truth) {
                let outcome = replay.feedback(FeedbackEvent {
                    seq,
                    truth: truth.clone(),
                    stored: None,
                    more: false,
                })?;
                if let ShapleyMethod::Sampled { std_error: se, .. } = &outcome.credit.method {
                    let mut full = vec![0.0; inf.w_used.len()];
                    for (a, &i) in inf.signals.coalition.iter().enumerate() {
                        full[i] = se[a];
                    }
                    std_error = Some(full);
                }
                phi = Some(outcome.phi);
            }
            out.push(RoundOutcome {
                id: pr.id.clone(),
                history,
                q: inf.q,
                thresholds: inf.thresholds,
                pred: inf.pred,
                w_used: inf.w_used,
                phi,
                shapley_std_error: std_error,
                w_after: replay.engine().reputations().to_vec(),
                latency_s: start.elapsed().as_secs_f64() + gemm_s,
            });
            progress(t + 1);
        }
        t0 = t1;
    }
    Ok((engine, out))
}

/// The methods `batch_knn` batches. `adaptive` is replayed on the per-query path, the one the
/// service runs, so that `eval` under the default method answers as the service does bit for
/// bit (`tests/process/replay.rs`); a GEMM's cosines differ from `dot`'s in the last bits.
const BATCHED: [Method; 1] = [Method::Paper];

/// Scores the method on the scored rounds (after the history, with truth).
pub fn score_method(
    rounds: &[ParsedRound],
    outcomes: &[RoundOutcome],
    l: usize,
    eps: f64,
) -> Scores {
    let mut acc = MetricsAcc::new(l, eps);
    for (r, o) in rounds.iter().zip(outcomes) {
        if let (false, Some(truth)) = (o.history, &r.truth) {
            acc.add(&o.pred, &o.q, truth, Some(o.latency_s));
        }
    }
    acc.finish()
}

/// Scores the baselines on the same rounds: each reporter alone (its label set; a round it missed
/// counts as an empty set), and majority vote (on when more than half of the present reporters
/// report it). Their 0/1 predictions are scored as probabilities, clipped to `eps`.
pub fn score_baselines(
    rounds: &[ParsedRound],
    n_hist: usize,
    reporters: &[String],
    l: usize,
    eps: f64,
) -> Vec<(String, Scores)> {
    let n = reporters.len();
    let mut accs: Vec<MetricsAcc> = (0..=n).map(|_| MetricsAcc::new(l, eps)).collect();
    for r in rounds.iter().skip(n_hist) {
        let Some(truth) = &r.truth else { continue };
        for (i, acc) in accs.iter_mut().enumerate().take(n) {
            let pred: Vec<u8> = (0..l)
                .map(|k| {
                    if r.round.present[i] {
                        r.round.reports[i * l + k]
                    } else {
                        0
                    }
                })
                .collect();
            let prob: Vec<f64> = pred.iter().map(|&p| p as f64).collect();
            acc.add(&pred, &prob, truth, None);
        }
        let pred = majority_vote(&r.round, l);
        let prob: Vec<f64> = pred.iter().map(|&p| p as f64).collect();
        accs[n].add(&pred, &prob, truth, None);
    }
    let mut out: Vec<(String, Scores)> = reporters
        .iter()
        .zip(&accs)
        .map(|(name, a)| (format!("{name} alone"), a.finish()))
        .collect();
    out.push(("majority vote".into(), accs[n].finish()));
    out
}
