//! The repeated game's state and its moves: `infer` (read-only), `observe` (a stored round) and
//! `credit` + `apply` (feedback). Splitting feedback into a pure `credit` and a mutating `apply`
//! lets the service compute and persist an outcome before it touches the in-memory state, and
//! lets a replay ([`crate::replay`]) take the exact same steps.
//!
//! The engine keeps what every method shares: the ontology, the reporters, their reputations and
//! statistics, the labelled-round counter and the context dimension. Everything else belongs to
//! the method it runs (`crate::method`), which it calls with a read-only view of that state.

use crate::bank::Bank;
use crate::config::{FusionConfig, Method};
use crate::error::FusionError;
use crate::method::adaptive::Scan;
use crate::method::{Ctx, MethodState};
use crate::ontology::Ontology;
use crate::signals::{clip, Credit, ShapleyMethod, Signals};
use crate::threshold::ThresholdFitter;
use serde::{Deserialize, Serialize};
use std::collections::{BTreeMap, HashMap};

/// One line of docs/PAPER-METHOD.md §8: the data exchange format of `eval` and `POST /v1/fuse`.
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
#[derive(Debug, Clone, PartialEq)]
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

/// The truth byte of a label that a (partial) feedback does not give: truth vectors hold 0, 1
/// or `UNKNOWN` per label. Every method learns only from the labels that are 0 or 1; a round
/// labelled in several feedbacks is learned from each one's labels as it comes.
pub const UNKNOWN: u8 = 2;

/// A labelled round as the methods learn from it.
#[derive(Debug, Clone, PartialEq)]
pub struct LabelledRound {
    /// Inference order of the round (ties in similarity go to the older one).
    pub seq: u64,
    pub round: Round,
    /// Per label 0, 1 or [`UNKNOWN`]: what this feedback teaches. A second feedback on a round
    /// carries only the labels it adds or overrides; the methods merge it into what the first
    /// left (the round's bank or pool entry takes the new values).
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

impl Inference {
    /// Thresholds the posteriors (`q >= t` per label) into the round's inference; the one
    /// decision rule both methods serve.
    pub(crate) fn decide(
        signals: Signals,
        q: Vec<f64>,
        thresholds: Vec<f64>,
        w: &[f64],
        scan: Option<Scan>,
    ) -> Self {
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
            w_used: w.to_vec(),
            scan,
        }
    }
}

/// One label's explanation: the prior and each member's weighted, guardrailed LLR.
#[derive(Debug, Clone, PartialEq)]
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

/// Per-reporter statistics kept across rounds (PAPER-METHOD.md §4).
#[derive(Debug, Clone, Default, PartialEq, Serialize, serde::Deserialize)]
pub struct ReporterStats {
    /// Labelled rounds in which the reporter was present.
    pub rounds_credited: u64,
    pub phi_sum: f64,
    pub last_phi: f64,
    /// Discounted utility `U_i = sum delta^(t-1) u_i`.
    pub utility: f64,
}

/// The version of the engine's serialised layout (its `serde` form, field by field, down to
/// the methods' state). A stored copy written under another layout is not read back: the store
/// then replays the events instead. Bump it with any change to a field of the engine or of the
/// state it owns; the `layout_is_pinned` test fails until it is bumped and its digest updated.
pub const ENGINE_LAYOUT: u32 = 9;

/// The engine: shared state plus the configured method's own. Serialisable so that the store
/// can keep a snapshot and replay only the events after it; a snapshot read back is the very
/// engine that was written (every `f64` by its bits), so snapshot plus tail equals a full replay.
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
pub struct Engine {
    #[serde(with = "crate::sorted_map::as_json")]
    cfg: FusionConfig,
    #[serde(with = "crate::sorted_map::as_json")]
    ontology: Ontology,
    reporters: Vec<String>,
    #[serde(with = "crate::sorted_map")]
    index: HashMap<String, usize>,
    /// The context dimension in force: configured, or fixed by the first stored round.
    dim: Option<usize>,
    /// Reputations, one per reporter, summing to one.
    w: Vec<f64>,
    stats: Vec<ReporterStats>,
    /// Labelled rounds applied: the clock every method's decay and cold-start rules read.
    labelled: u64,
    method: MethodState,
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
        let mut method = MethodState::new(&cfg, n, ontology.len());
        if let Some(d) = cfg.dim {
            method.set_dim(d);
        }
        Ok(Self {
            dim: cfg.dim,
            w: vec![1.0 / n as f64; n],
            stats: vec![ReporterStats::default(); n],
            labelled: 0,
            method,
            index,
            reporters,
            ontology,
            cfg,
        })
    }

    /// The shared state as the method sees it.
    fn ctx(&self) -> Ctx<'_> {
        Ctx {
            cfg: &self.cfg,
            n: self.reporters.len(),
            l: self.ontology.len(),
            w: &self.w,
            labelled: self.labelled,
        }
    }

    /// The shared state and the method, borrowed apart, for the calls that change the method.
    fn split(&mut self) -> (Ctx<'_>, &mut MethodState) {
        let cx = Ctx {
            cfg: &self.cfg,
            n: self.reporters.len(),
            l: self.ontology.len(),
            w: &self.w,
            labelled: self.labelled,
        };
        (cx, &mut self.method)
    }

    pub fn config(&self) -> &FusionConfig {
        &self.cfg
    }

    /// Whether `other` was built from the same configuration, ontology and reporters. A stored
    /// copy of one engine ([`ENGINE_LAYOUT`], the store's snapshots) may stand in for a replay
    /// into the other only then: any difference (a changed `[fusion]` setting, a reporter added)
    /// would make the copy disagree with what the replay gives.
    pub fn same_setup(&self, other: &Engine) -> bool {
        self.cfg == other.cfg
            && self.ontology == other.ontology
            && self.reporters == other.reporters
    }
    /// The fusion method this engine runs.
    pub fn method(&self) -> Method {
        self.cfg.method
    }
    /// Whether [`Engine::observe`] changes anything: the method learns from unlabelled rounds
    /// (`adaptive`), so a rebuild must replay every stored round, not only the labelled ones.
    pub fn observes(&self) -> bool {
        self.method.observes()
    }

    /// `adaptive`'s pool: (labelled, unlabelled) entries, the second bounded by
    /// `[fusion.adaptive] pool_max`. `None` under `paper`.
    pub fn pool_sizes(&self) -> Option<(usize, usize)> {
        self.method.pool_sizes()
    }

    /// Whether `adaptive`'s scans go through its approximate index (false under `paper`).
    pub fn approximate_knn(&self) -> bool {
        self.method.approximate_knn()
    }

    /// `adaptive`'s approximate index: whether it is in use, and the share of the exact
    /// neighbours (by cosine, `max(k, k_prior)` per query) that its scans find for these
    /// unit-norm contexts (1 when the scans are exact). `None` under `paper`.
    pub fn neighbour_recall(&self, contexts: &[Vec<f64>]) -> Option<(bool, f64)> {
        self.method.neighbour_recall(contexts, self.labelled())
    }

    /// The predictor deciding rounds now under `adaptive` (docs/METHOD.md §3): the whole-pool
    /// Dawid–Skene, the context-aware model, majority vote, the paper rule or the mean of the
    /// last two. `None` under `paper`, whose one
    /// predictor is the method itself.
    pub fn serving(&self) -> Option<crate::method::adaptive::Predictor> {
        self.method.serving(&self.ctx())
    }

    /// What `adaptive`'s `paper` candidate (PAPER-METHOD.md's rule over the pool's latest
    /// labelled rounds) answers for a round: posteriors and thresholds. `None` under `paper` or
    /// when the candidate is left out.
    pub fn paper_candidate(&self, round: &Round) -> Option<(Vec<f64>, Vec<f64>)> {
        self.method.paper_candidate(&self.ctx(), round)
    }

    /// The candidates' recent scores the choice of [`Engine::serving`] is made on (`adaptive`);
    /// `None` under `paper`.
    pub fn candidate_scores(&self) -> Option<Vec<crate::method::adaptive::CandidateScore>> {
        self.method.candidate_scores(&self.ctx())
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
    /// The contexts the method searches: the paper method's bank of labelled rounds under `paper`, the pool
    /// of every observed round under `adaptive` (whose truths there are unused: the pool keeps
    /// soft truths).
    pub fn bank(&self) -> &Bank {
        self.method.bank()
    }
    /// The method's threshold fitter (under `adaptive` the served thresholds are its fit shrunk
    /// toward `threshold_initial`; see [`Inference::thresholds`]).
    pub fn threshold(&self) -> &ThresholdFitter {
        self.method.threshold()
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
                self.method.set_dim(d);
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

    /// Validates a docs/PAPER-METHOD.md §8 record into a round and its optional truth. Nothing is changed.
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

    /// Whether a round's sizes match this engine's reporters and labels.
    pub fn fits(&self, round: &Round) -> bool {
        let (n, l) = (self.reporters.len(), self.ontology.len());
        round.present.len() == n && round.reports.len() == n * l
    }

    /// Infers a round against the state as it stands (PAPER-METHOD.md §2–3).
    pub fn infer(&self, round: &Round) -> Inference {
        self.method.infer(&self.ctx(), round, None)
    }

    /// Like [`Engine::infer`], with the similarities computed elsewhere (a batched GEMM):
    /// `sims[seq]` is the round's cosine to the round numbered `seq`, for every `seq` the
    /// method's [`Engine::bank`] holds. Both methods search with them instead of scanning.
    pub fn infer_with_sims(&self, round: &Round, sims: &[f64]) -> Inference {
        self.method.infer(&self.ctx(), round, Some(sims))
    }

    /// A round was stored (after `/v1/fuse`, or a rounds-file line): under `adaptive` it joins
    /// the pool with its soft truth (the inference's posterior), and the per-event EM chunk
    /// runs. Under `paper`, rounds change nothing until they are labelled. Idempotent per `seq`;
    /// call it in the order rounds were stored, with the inference the round got.
    pub fn observe(&mut self, seq: u64, round: &Round, inf: &Inference) -> Result<(), FusionError> {
        self.observe_ahead(seq, round, inf, None)
    }

    /// [`Engine::observe`], told the context of the round that will be inferred next (an
    /// import reads ahead): under `adaptive` with its approximate index in use, that round's
    /// index search then runs on the helper thread beside this round's EM work. The engine it
    /// leaves and every later result are those of [`Engine::observe`], bit for bit; it only
    /// takes less time.
    pub fn observe_ahead(
        &mut self,
        seq: u64,
        round: &Round,
        inf: &Inference,
        next_context: Option<(&[f64], &crate::Beside)>,
    ) -> Result<(), FusionError> {
        if !self.method.observes() {
            return Ok(());
        }
        if !self.fits(round) {
            return Err(FusionError::Config(
                "observed round has sizes that do not match the engine".into(),
            ));
        }
        if !self.method.wants(&self.ctx(), seq) {
            return Ok(());
        }
        self.fix_dim(round.context.len())?;
        let (cx, method) = self.split();
        method.observe(&cx, seq, round, inf, next_context);
        Ok(())
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
    /// CURRENT reputations (PAPER-METHOD.md §5). Pure: the state is changed only by [`Engine::apply`].
    pub fn credit(
        &self,
        signals: &Signals,
        w_used: &[f64],
        truth: &[u8],
        seq: u64,
    ) -> FeedbackOutcome {
        let cfg = &self.cfg;
        let credit = signals.credit(cfg, truth, seq);
        let n = self.reporters.len();
        let phi = credit.by_reporter(&signals.coalition, n);
        let w_sum: f64 = w_used.iter().sum();
        let payoff = (0..n)
            .map(|i| phi[i] + cfg.payoff_alpha * cfg.payoff_prize * w_used[i] / w_sum)
            .collect();
        let w_before = self.w.clone();
        let w_after = if cfg.ablations.frozen_reputation {
            w_before.clone()
        } else {
            self.method
                .reputation(&self.ctx(), &w_before, &phi, &signals.coalition)
        };
        let (evidence, prior_logit) = self.method.calibration_inputs(signals);
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
    /// then the method's side (its bank or pool, correlations, calibration, threshold refit),
    /// then the labelled-round counter advances.
    pub fn apply(
        &mut self,
        lr: &LabelledRound,
        outcome: Option<&FeedbackOutcome>,
    ) -> Result<(), FusionError> {
        self.fix_dim(lr.round.context.len())?;
        if let Some(o) = outcome {
            self.w.clone_from(&o.w_after);
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
        debug_assert_eq!(lr.q.len(), self.ontology.len());
        let (cx, method) = self.split();
        method.apply(&cx, lr, outcome);
        self.labelled += 1;
        Ok(())
    }
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
