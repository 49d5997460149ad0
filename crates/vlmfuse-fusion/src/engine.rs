//! The repeated game's state and its two moves: `infer` (read-only) and `credit` + `apply`
//! (feedback). Splitting feedback into a pure `credit` and a mutating `apply` lets the service
//! compute and persist an outcome before it touches the in-memory state, and lets `eval` replay
//! the exact same steps.

use crate::adaptive::{Adaptive, Scan};
use crate::bank::{Bank, Neighbour};
use crate::config::{FusionConfig, Method};
use crate::corr::CorrWindow;
use crate::error::FusionError;
use crate::ontology::Ontology;
use crate::signals::{clip, Credit, ShapleyMethod, Signals};
use crate::threshold::ThresholdFitter;
use serde::{Deserialize, Serialize};
use std::collections::{BTreeMap, HashMap};

/// One line of SPEC §8: the data exchange format of `eval` and `POST /v1/fuse`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RoundRecord {
    #[serde(default)]
    pub id: Option<String>,
    pub context: Vec<f64>,
    pub reports: BTreeMap<String, Vec<String>>,
    #[serde(default)]
    pub truth: Option<Vec<String>>,
}

/// A validated round: unit-norm context and reports indexed by reporter and label.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Round {
    pub context: Vec<f64>,
    /// One flag per configured reporter.
    pub present: Vec<bool>,
    /// `n * L` reports, 0 where absent.
    pub reports: Vec<u8>,
}

impl Round {
    pub fn coalition(&self) -> Vec<usize> {
        (0..self.present.len())
            .filter(|&i| self.present[i])
            .collect()
    }
}

/// A labelled round as the bank, the correlation window and the threshold fit need it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LabelledRound {
    /// Inference order of the round (ties in similarity go to the older one).
    pub seq: u64,
    pub round: Round,
    pub truth: Vec<u8>,
    /// The posteriors the round got at inference time (for the threshold fit).
    pub q: Vec<f64>,
}

/// What inference produced for one round.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Inference {
    pub signals: Signals,
    /// Fused posteriors per label, clipped.
    pub q: Vec<f64>,
    /// Threshold per label in force for this round.
    pub thresholds: Vec<f64>,
    pub pred: Vec<u8>,
    /// The whole reputation vector at inference (all `n` reporters).
    pub w_used: Vec<f64>,
    /// `adaptive` only: the pass over the pool that inference made, reused when the round
    /// joins the pool ([`Engine::observe`]). Not persisted: without it `observe` scans again.
    #[serde(skip)]
    pub scan: Option<Scan>,
}

/// One label's explanation: the prior and each member's weighted, guardrailed LLR.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LabelExplanation {
    pub prior: f64,
    /// `(reporter index, w_i * lambda~_ik)` over the coalition.
    pub contributions: Vec<(usize, f64)>,
    /// `logit(pi) + sum` before the sigmoid.
    pub logit: f64,
}

/// The outcome of feedback on a round, computed before anything changes.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FeedbackOutcome {
    pub credit: Credit,
    /// Credit per reporter (all `n`), 0 for reporters absent from the round.
    pub phi: Vec<f64>,
    /// Stage payoff per reporter.
    pub payoff: Vec<f64>,
    pub w_before: Vec<f64>,
    pub w_after: Vec<f64>,
    /// `adaptive` only: the round's inference-time evidence and prior log-odds per label (the
    /// two parts of the raw fused logit), which the calibration is fitted on. Empty under
    /// `paper`.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub evidence: Vec<f64>,
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub prior_logit: Vec<f64>,
}

/// Per-reporter statistics kept across rounds (SPEC §4).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct ReporterStats {
    /// Labelled rounds in which the reporter was present.
    pub rounds_credited: u64,
    pub phi_sum: f64,
    pub last_phi: f64,
    /// Discounted utility `U_i = sum delta^(t-1) u_i`.
    pub utility: f64,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Engine {
    pub(crate) cfg: FusionConfig,
    pub(crate) ontology: Ontology,
    pub(crate) reporters: Vec<String>,
    #[serde(skip)]
    index: HashMap<String, usize>,
    pub(crate) dim: Option<usize>,
    pub(crate) bank: Bank,
    pub(crate) corr: CorrWindow,
    pub(crate) w: Vec<f64>,
    pub(crate) threshold: ThresholdFitter,
    stats: Vec<ReporterStats>,
    pub(crate) labelled: u64,
    /// `method = "adaptive"`: the pool of every observed round, the calibration, the decayed
    /// whole-pool sums. `None` under `paper`.
    #[serde(default)]
    pub(crate) adaptive: Option<Adaptive>,
}

impl Engine {
    pub fn new(
        cfg: FusionConfig,
        ontology: Ontology,
        reporters: Vec<String>,
    ) -> Result<Self, FusionError> {
        cfg.validate().map_err(FusionError::Config)?;
        if reporters.is_empty() {
            return Err(FusionError::Config(
                "at least one reporter is needed".into(),
            ));
        }
        let mut index = HashMap::new();
        for (i, r) in reporters.iter().enumerate() {
            if r.trim().is_empty() {
                return Err(FusionError::Config("a reporter has an empty name".into()));
            }
            if index.insert(r.clone(), i).is_some() {
                return Err(FusionError::Config(format!(
                    "reporter {r:?} is named twice"
                )));
            }
        }
        let n = reporters.len();
        let l = ontology.len();
        let mut bank = Bank::new(n, l);
        if let Some(d) = cfg.dim {
            bank.set_dim(d);
        }
        let (threshold, adaptive) = match cfg.method {
            Method::Paper => (ThresholdFitter::new(&cfg, l), None),
            Method::Adaptive => {
                // The adaptive method has its own cold-start rule for the threshold.
                let tcfg = FusionConfig {
                    threshold_initial: cfg.adaptive.threshold_initial,
                    threshold_min_rounds: cfg.adaptive.threshold_min_rounds,
                    ..cfg.clone()
                };
                (
                    ThresholdFitter::new(&tcfg, l),
                    Some(Adaptive::new(&cfg, n, l)),
                )
            }
        };
        Ok(Self {
            dim: cfg.dim,
            corr: CorrWindow::new(n, l, cfg.corr_window),
            w: vec![1.0 / n as f64; n],
            threshold,
            adaptive,
            stats: vec![ReporterStats::default(); n],
            labelled: 0,
            bank,
            index,
            reporters,
            ontology,
            cfg,
        })
    }

    /// Rebuilds the name index after deserialisation.
    pub fn reindex(&mut self) {
        self.index = self
            .reporters
            .iter()
            .enumerate()
            .map(|(i, r)| (r.clone(), i))
            .collect();
    }

    pub fn config(&self) -> &FusionConfig {
        &self.cfg
    }
    /// The fusion method this engine runs.
    pub fn method(&self) -> Method {
        self.cfg.method
    }

    /// Whether the decisions served now are majority vote's: `adaptive`'s vote fallback, until
    /// the model has beaten the vote on the labelled rounds. Always false under `paper`.
    pub fn serving_vote(&self) -> bool {
        self.adaptive.is_some() && self.ad_voting()
    }
    pub fn ontology(&self) -> &Ontology {
        &self.ontology
    }
    pub fn reporters(&self) -> &[String] {
        &self.reporters
    }
    pub fn reporter_index(&self, name: &str) -> Option<usize> {
        self.index.get(name).copied()
    }
    pub fn reputations(&self) -> &[f64] {
        &self.w
    }
    pub fn stats(&self) -> &[ReporterStats] {
        &self.stats
    }
    pub fn labelled(&self) -> u64 {
        self.labelled
    }
    pub fn bank(&self) -> &Bank {
        &self.bank
    }
    pub fn corr(&self) -> &CorrWindow {
        &self.corr
    }
    pub fn threshold(&self) -> &ThresholdFitter {
        &self.threshold
    }
    /// The context dimension in force: configured, or taken from the first stored round.
    pub fn dim(&self) -> Option<usize> {
        self.dim
    }

    /// Fixes the context dimension (the service does this when it stores its first round, so
    /// that a later round of another dimension is refused even before any feedback).
    pub fn fix_dim(&mut self, d: usize) -> Result<(), FusionError> {
        match self.dim {
            Some(e) if e != d => Err(FusionError::Dimension {
                expected: e,
                got: d,
            }),
            _ => {
                self.dim = Some(d);
                self.bank.set_dim(d);
                if let Some(ad) = self.adaptive.as_mut() {
                    ad.pool.bank.set_dim(d);
                }
                Ok(())
            }
        }
    }

    /// Checks and normalises a context: finite, non-zero, of the dimension in force.
    pub fn normalise_context(&self, context: &[f64]) -> Result<Vec<f64>, FusionError> {
        if context.is_empty() {
            return Err(FusionError::EmptyContext);
        }
        if let Some(e) = self.dim {
            if e != context.len() {
                return Err(FusionError::Dimension {
                    expected: e,
                    got: context.len(),
                });
            }
        }
        if let Some(i) = context.iter().position(|v| !v.is_finite()) {
            return Err(FusionError::NonFinite { index: i });
        }
        // Scale by the largest magnitude first so that squaring cannot overflow (a context of
        // 1e300s is a direction like any other) nor underflow to a false zero.
        let max = context.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        if max == 0.0 {
            return Err(FusionError::ZeroContext);
        }
        let scaled: Vec<f64> = context.iter().map(|v| v / max).collect();
        let norm = scaled.iter().map(|v| v * v).sum::<f64>().sqrt();
        Ok(scaled.iter().map(|v| v / norm).collect())
    }

    /// Validates a SPEC §8 record into a round and its optional truth. Nothing is changed.
    pub fn parse(&self, rec: &RoundRecord) -> Result<(Round, Option<Vec<u8>>), FusionError> {
        let context = self.normalise_context(&rec.context)?;
        let n = self.reporters.len();
        let l = self.ontology.len();
        let mut present = vec![false; n];
        let mut reports = vec![0u8; n * l];
        for (name, labels) in &rec.reports {
            if name.trim().is_empty() {
                return Err(FusionError::EmptyReporterName);
            }
            let i = self
                .reporter_index(name)
                .ok_or_else(|| FusionError::UnknownReporter(name.clone()))?;
            present[i] = true;
            for lab in labels {
                let k = self
                    .ontology
                    .lookup(lab)
                    .ok_or_else(|| FusionError::UnknownLabel {
                        label: lab.clone(),
                        whose: format!("reporter {name:?}"),
                    })?;
                reports[i * l + k] = 1;
            }
        }
        if !present.iter().any(|&p| p) {
            return Err(FusionError::EmptyCoalition);
        }
        let truth = match &rec.truth {
            None => None,
            Some(t) => Some(self.encode_truth(t)?),
        };
        Ok((
            Round {
                context,
                present,
                reports,
            },
            truth,
        ))
    }

    /// Encodes ground-truth label names, naming the first one outside the ontology.
    pub fn encode_truth<S: AsRef<str>>(&self, labels: &[S]) -> Result<Vec<u8>, FusionError> {
        let mut y = vec![0u8; self.ontology.len()];
        for lab in labels {
            let lab = lab.as_ref();
            let k = self
                .ontology
                .lookup(lab)
                .ok_or_else(|| FusionError::UnknownLabel {
                    label: lab.to_string(),
                    whose: "truth".into(),
                })?;
            y[k] = 1;
        }
        Ok(y)
    }

    /// Infers a round against the state as it stands (SPEC §2–3).
    pub fn infer(&self, round: &Round) -> Inference {
        if self.adaptive.is_some() {
            return self.ad_infer(round);
        }
        let nb = if self.bank.is_empty() || self.cfg.ablations.no_context {
            Vec::new()
        } else {
            self.bank
                .top_exact(&round.context, self.cfg.k.max(self.cfg.k_prior))
        };
        self.infer_from(round, &nb)
    }

    /// Like [`Engine::infer`], with the bank similarities computed elsewhere (a batched GEMM).
    /// Under `adaptive` the pool (not SPEC's bank) is searched and `sims` are ignored.
    pub fn infer_with_sims(&self, round: &Round, sims: &[f64]) -> Inference {
        if self.adaptive.is_some() {
            return self.ad_infer(round);
        }
        let nb = if self.bank.is_empty() || self.cfg.ablations.no_context {
            Vec::new()
        } else {
            self.bank.top(sims, self.cfg.k.max(self.cfg.k_prior))
        };
        self.infer_from(round, &nb)
    }

    fn infer_from(&self, round: &Round, nb: &[Neighbour]) -> Inference {
        let signals = self.signals(round, nb);
        let q = signals.full_posterior();
        let thresholds = self.threshold.thresholds().to_vec();
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
            scan: None,
        }
    }

    /// A round was stored without truth (after `/v1/fuse`, or a rounds-file line): under
    /// `adaptive` it joins the pool with its soft truth (the inference's posterior), and the
    /// per-event EM chunk runs. Under `paper`, unlabelled rounds change nothing. Idempotent per
    /// `seq`; call it in the order rounds were stored, with the inference the round got.
    pub fn observe(&mut self, seq: u64, round: &Round, inf: &Inference) -> Result<(), FusionError> {
        if self.adaptive.is_none() {
            return Ok(());
        }
        if round.present.len() != self.reporters.len()
            || round.reports.len() != self.reporters.len() * self.ontology.len()
        {
            return Err(FusionError::Config(
                "observed round has sizes that do not match the engine".into(),
            ));
        }
        self.ad_observe(seq, round, inf)
    }

    fn signals(&self, round: &Round, nb: &[Neighbour]) -> Signals {
        let cfg = &self.cfg;
        let l = self.ontology.len();
        let coalition = round.coalition();
        let p = coalition.len();
        let mut theta_pos = vec![0.5; p * l];
        let mut theta_neg = vec![0.5; p * l];
        // Empty bank: SPEC fixes theta and pi at 0.5 (no signal), whatever the Beta priors.
        let mut prior = vec![0.5; l];
        if !self.bank.is_empty() {
            // Sums a+, b+, a-, b- per member and label, and kernel mass and positives for pi.
            let mut acc = vec![[0.0f64; 4]; p * l];
            let mut pi_mass = 0.0;
            let mut pi_pos = vec![0.0; l];
            if cfg.ablations.no_context {
                for (a, &i) in coalition.iter().enumerate() {
                    for k in 0..l {
                        let c = self.bank.global_counts(i, k);
                        acc[a * l + k] = [c[0] as f64, c[1] as f64, c[2] as f64, c[3] as f64];
                    }
                }
                pi_mass = self.bank.len() as f64;
                for (k, v) in pi_pos.iter_mut().enumerate() {
                    *v = self.bank.global_positives(k) as f64;
                }
            } else {
                let kappa: Vec<f64> = nb.iter().map(|n| n.sim.max(0.0).powf(cfg.tau)).collect();
                for (idx, n) in nb.iter().enumerate().take(cfg.k) {
                    let kp = kappa[idx];
                    for (a, &i) in coalition.iter().enumerate() {
                        if !self.bank.present(n.pos, i) {
                            continue;
                        }
                        for k in 0..l {
                            let r = self.bank.report(n.pos, i, k);
                            let y = self.bank.truth(n.pos, k);
                            let cell = match (r, y) {
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
                    pi_mass += kappa[idx];
                    for (k, v) in pi_pos.iter_mut().enumerate() {
                        if self.bank.truth(n.pos, k) != 0 {
                            *v += kappa[idx];
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
                    (cfg.prior_alpha + pi_pos[k]) / (cfg.prior_alpha + cfg.prior_beta + pi_mass);
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
                        rho[(a * p + b) * l + k] =
                            self.corr.rho(coalition[a], coalition[b], k, cfg.rho_max);
                    }
                }
            }
        }
        let mut reports = Vec::with_capacity(p * l);
        for &i in &coalition {
            reports.extend_from_slice(&round.reports[i * l..(i + 1) * l]);
        }
        let w = coalition.iter().map(|&i| self.w[i]).collect();
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

    /// Per-label explanation of an inference: prior and each member's weighted, guardrailed LLR.
    pub fn explain(&self, inf: &Inference) -> Vec<LabelExplanation> {
        let s = &inf.signals;
        let lam = s.llr();
        let lp = s.prior_logit();
        let c = s.contributions(&lam, &|_| true);
        (0..s.l)
            .map(|k| {
                let contributions: Vec<(usize, f64)> = s
                    .coalition
                    .iter()
                    .enumerate()
                    .map(|(a, &i)| (i, c[a * s.l + k]))
                    .collect();
                LabelExplanation {
                    prior: clip(s.prior[k], s.eps),
                    logit: lp[k] + contributions.iter().map(|(_, v)| v).sum::<f64>(),
                    contributions,
                }
            })
            .collect()
    }

    /// Credits a round from its stored signals and computes the reputation update against the
    /// CURRENT reputations (SPEC §5). Pure: the state is changed only by [`Engine::apply`].
    pub fn credit(
        &self,
        signals: &Signals,
        w_used: &[f64],
        truth: &[u8],
        seq: u64,
    ) -> FeedbackOutcome {
        let cfg = &self.cfg;
        let credit = if cfg.ablations.per_model_score {
            signals.per_model_score(truth)
        } else if signals.members() <= cfg.shapley_exact_max {
            signals.shapley_exact(truth)
        } else {
            let seed = cfg.shapley_seed ^ seq.wrapping_mul(0x9e37_79b9_7f4a_7c15);
            signals.shapley_sampled(truth, cfg.shapley_samples, seed)
        };
        let n = self.reporters.len();
        let mut phi = vec![0.0; n];
        for (a, &i) in signals.coalition.iter().enumerate() {
            phi[i] = credit.phi[a];
        }
        let w_sum: f64 = w_used.iter().sum();
        let payoff = (0..n)
            .map(|i| phi[i] + cfg.payoff_alpha * cfg.payoff_prize * w_used[i] / w_sum)
            .collect();
        let w_before = self.w.clone();
        let w_after = if cfg.ablations.frozen_reputation {
            w_before.clone()
        } else {
            match cfg.method {
                Method::Paper => reputation_update(&w_before, &phi, cfg.eta),
                Method::Adaptive => self.ad_reputation(&w_before, &phi, &signals.coalition),
            }
        };
        let (evidence, prior_logit) = match cfg.method {
            Method::Paper => (Vec::new(), Vec::new()),
            Method::Adaptive => (signals.evidence(), signals.prior_logit()),
        };
        FeedbackOutcome {
            credit,
            phi,
            payoff,
            w_before,
            w_after,
            evidence,
            prior_logit,
        }
    }

    /// Applies a labelled round: the reputation update and statistics of its outcome (if given),
    /// the bank, the correlation window and the threshold refit.
    pub fn apply(
        &mut self,
        lr: &LabelledRound,
        outcome: Option<&FeedbackOutcome>,
    ) -> Result<(), FusionError> {
        let d = lr.round.context.len();
        self.fix_dim(d)?;
        if let Some(o) = outcome {
            self.w.clone_from(&o.w_after);
            if self.adaptive.is_some() {
                self.ad_credit_push(&o.phi, &lr.round.present);
            }
            let t = self.labelled as i32; // t - 1 for the round being labelled now
            let disc = self.cfg.payoff_delta.powi(t);
            for (i, st) in self.stats.iter_mut().enumerate() {
                if lr.round.present[i] {
                    st.rounds_credited += 1;
                    st.phi_sum += o.phi[i];
                    st.last_phi = o.phi[i];
                }
                st.utility += disc * o.payoff[i];
            }
        }
        if self.adaptive.is_none() {
            self.bank.push(
                lr.seq,
                &lr.round.context,
                &lr.round.present,
                &lr.round.reports,
                &lr.truth,
            );
        }
        let l = self.ontology.len();
        self.corr
            .push(&lr.round.present, &lr.round.reports, &lr.truth);
        debug_assert_eq!(lr.q.len(), l);
        if self.adaptive.is_some() {
            // Also pushes to the threshold fitter (what it fits on depends on the mode).
            self.ad_apply(lr, outcome);
        } else {
            self.threshold.push(&lr.q, &lr.truth);
        }
        self.labelled += 1;
        if self.adaptive.is_some() {
            self.ad_after_apply();
        }
        Ok(())
    }

    /// Sets the reputations and statistics directly, for a store that rebuilds the engine from
    /// its tables (the bank side is rebuilt with `apply(.., None)`).
    pub fn restore(&mut self, w: Vec<f64>, stats: Vec<ReporterStats>) -> Result<(), FusionError> {
        if w.len() != self.reporters.len() || stats.len() != self.reporters.len() {
            return Err(FusionError::Config(
                "restored state has the wrong number of reporters".into(),
            ));
        }
        self.w = w;
        self.stats = stats;
        Ok(())
    }
}

/// Fixed-share mixing `w <- (1 - alpha) w + alpha / n` (docs/METHOD.md §6); `alpha = 0` returns
/// `w` untouched.
pub fn fixed_share(w: &[f64], alpha: f64) -> Vec<f64> {
    if alpha == 0.0 {
        return w.to_vec();
    }
    let n = w.len() as f64;
    w.iter().map(|&x| (1.0 - alpha) * x + alpha / n).collect()
}

/// `w_i <- w_i exp(eta phi_i) / sum_j w_j exp(eta phi_j)`. The exponent is shifted by its maximum,
/// which cancels in the ratio and keeps `exp` from overflowing on a huge credit.
pub fn reputation_update(w: &[f64], phi: &[f64], eta: f64) -> Vec<f64> {
    let m = phi
        .iter()
        .map(|p| eta * p)
        .fold(f64::NEG_INFINITY, f64::max);
    let raw: Vec<f64> = w
        .iter()
        .zip(phi)
        .map(|(wi, p)| wi * (eta * p - m).exp())
        .collect();
    let s: f64 = raw.iter().sum();
    raw.iter().map(|r| r / s).collect()
}

impl ShapleyMethod {
    pub fn name(&self) -> &'static str {
        match self {
            ShapleyMethod::Exact => "exact",
            ShapleyMethod::Sampled { .. } => "sampled",
            ShapleyMethod::PerModelScore => "per_model_score",
        }
    }
}
