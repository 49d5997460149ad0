//! The paper's evaluation protocol (SPEC §9, `eval`): rounds in file order, each first predicted
//! with the state as it stands and then learned from if it has truth. The first `split` share is
//! history and is not scored.
//!
//! With `batch_knn`, the similarities of a block of upcoming rounds to every earlier round are one
//! GEMM (faer) instead of one dot product per pair; each round then reads its row restricted to
//! what its bank holds at that moment, so the results are those of the per-query path.

use crate::config::{FusionConfig, Method};
use crate::engine::{Engine, LabelledRound, Round, RoundRecord};
use crate::error::FusionError;
use crate::metrics::{MetricsAcc, Scores};
use crate::ontology::Ontology;
use crate::signals::ShapleyMethod;
use faer::{Accum, MatMut, MatRef, Par};
use serde::{Deserialize, Serialize};
use std::collections::BTreeSet;
use std::time::Instant;

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

/// Every reporter name that appears in the records, sorted (SPEC §9).
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

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
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

/// Replays the rounds through the engine. `progress` is called with the number of rounds done.
pub fn replay(
    mut engine: Engine,
    rounds: &[ParsedRound],
    opts: &ReplayOptions,
    progress: &mut dyn FnMut(usize),
) -> Result<(Engine, Vec<RoundOutcome>), FusionError> {
    let n = rounds.len();
    let n_hist = history_len(n, opts.split);
    let mut out = Vec::with_capacity(n);
    // File index of every bank entry, in bank order.
    let mut bank_src: Vec<usize> = Vec::new();
    let block = (16_000_000 / n.max(1)).clamp(16, 512);
    let dim = rounds.first().map(|r| r.round.context.len()).unwrap_or(0);
    // The adaptive method searches its own pool (every observed round), not SPEC's bank.
    let batch = opts.batch_knn && engine.method() == Method::Paper;
    let mut keys: Vec<f64> = Vec::new();
    if batch {
        keys.reserve(n * dim);
        for r in rounds {
            keys.extend_from_slice(&r.round.context);
        }
    }
    let mut gram: Vec<f64> = Vec::new();
    let mut sims: Vec<f64> = Vec::new();
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
            let start = Instant::now();
            let inf = if batch {
                let row = &gram[(t - t0) * t1..(t - t0 + 1) * t1];
                sims.clear();
                sims.extend(bank_src.iter().map(|&s| row[s]));
                engine.infer_with_sims(&pr.round, &sims)
            } else {
                engine.infer(&pr.round)
            };
            let history = t < n_hist;
            let learning = history || !opts.frozen;
            let learn = pr.truth.is_some() && learning;
            if learning {
                // As the service does when it stores a round: under `adaptive` it joins the
                // pool (its label, if any, follows right after); under `paper` a no-op.
                engine.observe(t as u64, &pr.round, &inf)?;
            }
            let mut phi = None;
            let mut std_error = None;
            if learn {
                let truth = pr.truth.as_ref().expect("learn implies truth");
                let outcome = engine.credit(&inf.signals, &inf.w_used, truth, t as u64);
                if let ShapleyMethod::Sampled { std_error: se, .. } = &outcome.credit.method {
                    let mut full = vec![0.0; engine.reporters().len()];
                    for (a, &i) in inf.signals.coalition.iter().enumerate() {
                        full[i] = se[a];
                    }
                    std_error = Some(full);
                }
                let lr = LabelledRound {
                    seq: t as u64,
                    round: pr.round.clone(),
                    truth: truth.clone(),
                    q: inf.q.clone(),
                };
                engine.apply(&lr, Some(&outcome))?;
                bank_src.push(t);
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
                w_after: engine.reputations().to_vec(),
                latency_s: start.elapsed().as_secs_f64() + gemm_s,
            });
            progress(t + 1);
        }
        t0 = t1;
    }
    Ok((engine, out))
}

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
        let present = r.round.present.iter().filter(|&&p| p).count();
        let pred: Vec<u8> = (0..l)
            .map(|k| {
                let votes = (0..n)
                    .filter(|&i| r.round.present[i] && r.round.reports[i * l + k] != 0)
                    .count();
                (2 * votes > present) as u8
            })
            .collect();
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
