//! The JSON shapes of the API's answers (`openapi.yaml`'s schemas), built by the service and
//! serialised by the HTTP layer. Names (reporters, labels) appear only here: the engine and the
//! store speak indices.

use crate::service::writer::FeedbackDone;
use serde::{Serialize, Serializer};
use vlmfuse_fusion::{Engine, Inference, Label, ReporterStats, ShapleyMethod, ThresholdMode};
use vlmfuse_store::round_id;

/// A JSON object whose keys keep the order given (ontology or reporter order), which
/// `BTreeMap` would sort away.
pub struct Ordered<T>(pub Vec<(String, T)>);

impl<T: Serialize> Serialize for Ordered<T> {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.collect_map(self.0.iter().map(|(k, v)| (k, v)))
    }
}

#[derive(Serialize)]
pub struct LabelExplanationOut {
    /// Contextual prior `pi_k`.
    pub prior: f64,
    /// Each present reporter's weighted, guardrailed LLR `w_i * lambda~_ik`.
    pub contributions: Ordered<f64>,
    /// `logit(pi_k) + sum of contributions`: the posterior before the sigmoid.
    pub logit: f64,
}

#[derive(Serialize)]
pub struct FuseOut {
    pub round_id: String,
    /// The client's `id`, echoed when given.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub id: Option<String>,
    pub labels: Vec<String>,
    pub posteriors: Ordered<f64>,
    /// The fusion method that produced the posteriors: `paper` (PAPER-METHOD.md) or `adaptive`
    /// (docs/METHOD.md).
    pub method: &'static str,
    /// How the labels were decided (docs/METHOD.md §3): `model` (the method's posterior against
    /// its threshold; always under `paper`), `dawid_skene` (the whole-pool Dawid–Skene, which
    /// `adaptive` serves before labels say otherwise), `majority_vote`, `paper` (the paper rule
    /// over the latest labelled rounds) or `model_paper_mean`.
    pub decision: &'static str,
    /// Label id -> the predictor that decided it (one predictor decides a whole round).
    pub decided_by: Ordered<&'static str>,
    /// `adaptive` only: the deciding predictor's recent score on the labelled rounds, which the
    /// switch chose it on.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub decision_score: Option<vlmfuse_fusion::CandidateScore>,
    pub threshold: f64,
    /// Per-label thresholds, when they differ: the per-label threshold mode, or `adaptive`'s
    /// calibration mapping one threshold per label.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub thresholds: Option<Ordered<f64>>,
    pub coalition: Vec<String>,
    pub missing: Vec<String>,
    /// The reputations used for this round (all configured reporters).
    pub reputations: Ordered<f64>,
    pub explanation: Ordered<LabelExplanationOut>,
}

#[derive(Serialize)]
pub struct FuseBatchOut {
    pub rounds: Vec<Fused>,
}

/// A fused round in an answer: fused here, or (a replica that does not hold the writer lease)
/// by the writer, whose `/v1/fuse` answer is passed on as it came.
#[derive(Serialize)]
#[serde(untagged)]
pub enum Fused {
    Local(Box<FuseOut>),
    Remote(serde_json::Value),
}

pub fn fuse_out(engine: &Engine, seq: u64, id: Option<String>, inf: &Inference) -> FuseOut {
    let reporters = engine.reporters();
    let ontology = engine.ontology();
    let label = |k: usize| ontology.id(k).to_string();
    let l = ontology.len();
    let present = &inf.signals.coalition;
    let explanation = engine
        .explain(inf)
        .into_iter()
        .enumerate()
        .map(|(k, e)| {
            (
                label(k),
                LabelExplanationOut {
                    prior: e.prior,
                    contributions: Ordered(
                        e.contributions
                            .iter()
                            .map(|&(i, v)| (reporters[i].clone(), v))
                            .collect(),
                    ),
                    logit: e.logit,
                },
            )
        })
        .collect();
    FuseOut {
        round_id: round_id(seq),
        id,
        labels: ontology.decode(&inf.pred),
        posteriors: Ordered((0..l).map(|k| (label(k), inf.q[k])).collect()),
        method: engine.method().name(),
        decision: serving_predictor(engine),
        decided_by: Ordered(
            (0..l)
                .map(|k| (label(k), serving_predictor(engine)))
                .collect(),
        ),
        decision_score: serving_score(engine),
        threshold: inf.thresholds.first().copied().unwrap_or(0.5),
        thresholds: (engine.threshold().mode() == ThresholdMode::PerLabel
            || inf.thresholds.iter().any(|&t| t != inf.thresholds[0]))
        .then(|| Ordered((0..l).map(|k| (label(k), inf.thresholds[k])).collect())),
        coalition: present.iter().map(|&i| reporters[i].clone()).collect(),
        missing: (0..reporters.len())
            .filter(|i| !present.contains(i))
            .map(|i| reporters[i].clone())
            .collect(),
        reputations: Ordered(
            reporters
                .iter()
                .cloned()
                .zip(inf.w_used.iter().copied())
                .collect(),
        ),
        explanation: Ordered(explanation),
    }
}

/// A label this feedback gave that was not taken, and why.
#[derive(Serialize)]
pub struct IgnoredLabel {
    pub label: String,
    pub reason: String,
}

#[derive(Serialize)]
pub struct FeedbackOut {
    pub round_id: String,
    /// The round's labels known to be present, every feedback on it merged.
    pub labels: Vec<String>,
    /// The round's labels whose truth is known (present or not), and who gave each.
    pub known: Ordered<String>,
    /// Labels whose truth no feedback has given yet.
    pub unknown: Vec<String>,
    /// What this feedback taught: the labels it gave for the first time or overrode, with the
    /// value each now has. For a repeat, what the round's latest feedback taught.
    pub learned: Ordered<bool>,
    /// Labels this feedback gave that were not taken (a person's label stands).
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub ignored: Vec<IgnoredLabel>,
    /// Who gave the feedback whose credit is shown (this one, or for a repeat the round's
    /// latest).
    pub source: String,
    /// For a `signals` feedback: what the rules derived, with the evidence.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub derived: Option<vlmfuse_annotate::Annotation>,
    /// Shapley value of each reporter present in the round.
    pub shapley: Ordered<f64>,
    pub shapley_method: &'static str,
    /// Standard error of each sampled Shapley value (sampled method only).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub shapley_std_error: Option<Ordered<f64>>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub shapley_samples: Option<usize>,
    /// `v(N)`: the coalition's log-score gain over the prior (the sum of the Shapley values).
    pub value: f64,
    pub reputations_before: Ordered<f64>,
    pub reputations: Ordered<f64>,
    pub labelled_rounds: u64,
}

pub fn feedback_out(engine: &Engine, done: &FeedbackDone) -> FeedbackOut {
    let names = engine.reporters();
    let o = &done.feedback.outcome;
    let members = |v: &[f64]| {
        Ordered(
            done.coalition
                .iter()
                .zip(v)
                .map(|(&i, &x)| (names[i].clone(), x))
                .collect(),
        )
    };
    let all = |v: &[f64]| Ordered(names.iter().cloned().zip(v.iter().copied()).collect());
    let (se, samples) = match &o.credit.method {
        ShapleyMethod::Sampled { samples, std_error } => (Some(members(std_error)), Some(*samples)),
        _ => (None, None),
    };
    let ont = engine.ontology();
    let id = |k: usize| ont.labels()[k].id.clone();
    FeedbackOut {
        round_id: done.round_id.clone(),
        labels: ont.decode(&done.merged),
        known: Ordered(
            done.sources
                .iter()
                .enumerate()
                .filter_map(|(k, s)| s.clone().map(|s| (id(k), s)))
                .collect(),
        ),
        unknown: (0..done.merged.len())
            .filter(|&k| done.merged[k] > 1)
            .map(id)
            .collect(),
        learned: Ordered(
            done.learned
                .iter()
                .enumerate()
                .filter(|(_, &v)| v <= 1)
                .map(|(k, &v)| (id(k), v == 1))
                .collect(),
        ),
        ignored: done
            .ignored
            .iter()
            .map(|(k, r)| IgnoredLabel {
                label: id(*k),
                reason: r.clone(),
            })
            .collect(),
        source: done.feedback.source.clone(),
        derived: done.derived.clone(),
        shapley: members(&o.credit.phi),
        shapley_method: o.credit.method.name(),
        shapley_std_error: se,
        shapley_samples: samples,
        value: o.credit.v_full,
        reputations_before: all(&o.w_before),
        reputations: all(&o.w_after),
        labelled_rounds: done.feedback.labelled_order + 1,
    }
}

/// The predictor that decides rounds now, by the name responses, `/v1/state` and the operator
/// page give it (`model` under `paper`).
pub fn serving_predictor(engine: &Engine) -> &'static str {
    engine.serving().map_or("model", |p| p.name())
}

/// The serving predictor's recent score (`adaptive` with a gate; `None` otherwise).
pub fn serving_score(engine: &Engine) -> Option<vlmfuse_fusion::CandidateScore> {
    let now = engine.serving()?;
    engine
        .candidate_scores()?
        .into_iter()
        .find(|c| c.predictor == now)
}

/// `GET /v1/state`.
#[derive(Serialize)]
pub struct StateOut {
    /// The fusion method in force.
    pub method: &'static str,
    pub reputations: Ordered<f64>,
    pub labelled_rounds: u64,
    pub threshold: f64,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub thresholds: Option<Ordered<f64>>,
    pub reporters: Ordered<ReporterStats>,
    /// Rounds fused and stored (labelled or not).
    pub rounds: u64,
    /// Events the engine holds (stored rounds plus feedback events).
    pub state_seq: u64,
    /// On PostgreSQL: this replica's part, and how fresh its engine is.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub replica: Option<ReplicaOut>,
    /// Context dimension in force; null until the first round.
    pub dim: Option<usize>,
    /// `adaptive`'s pool: labelled and unlabelled entries (the latter bounded by
    /// `[fusion.adaptive] pool_max`); absent under `paper`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub pool: Option<PoolOut>,
    /// Which predictor serves every label now, and (under `adaptive`) the candidates' recent
    /// scores it is chosen on.
    pub serving: ServingOut,
}

#[derive(Serialize)]
pub struct ReplicaOut {
    /// `writer` (holds the lease) or `follower` (forwards writes, reads its own copy).
    pub role: &'static str,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub writer: Option<String>,
    pub synced_age_s: f64,
}

#[derive(Serialize)]
pub struct ServingOut {
    /// `dawid_skene`, `model`, `majority_vote`, `paper` or `model_paper_mean` (the same as
    /// each response's `decision`).
    pub predictor: &'static str,
    /// The `[fusion.adaptive] serve` rule in force (`switch`, `vote-fallback`, `model`);
    /// absent under `paper`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub rule: Option<&'static str>,
    /// `adaptive` only: each candidate's recent score on the labelled rounds (under `switch`
    /// discounted by `switch_discount`; under `vote-fallback` over every labelled round), which
    /// decides who serves (docs/METHOD.md §3).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub scores: Option<Vec<vlmfuse_fusion::CandidateScore>>,
}

#[derive(Serialize)]
pub struct PoolOut {
    pub labelled: usize,
    pub unlabelled: usize,
    /// The cap on unlabelled entries (0: none).
    pub max_unlabelled: usize,
    /// Whether neighbours are found through the approximate index (`[fusion.adaptive]
    /// ann_min` reached) rather than by the exact scan.
    pub approximate_knn: bool,
}

/// `GET /v1/ontology`.
#[derive(Serialize)]
pub struct OntologyOut {
    pub labels: Vec<Label>,
}

/// `POST /v1/infer`, per clip.
#[derive(Serialize)]
pub struct ReporterOut {
    pub text: String,
    pub labels: Vec<String>,
    pub latency_ms: f64,
    pub label_ms: f64,
    pub labeler: String,
}

#[derive(Serialize, Clone)]
pub struct ClipOut {
    #[serde(skip_serializing_if = "Option::is_none")]
    pub file_name: Option<String>,
    pub bytes: u64,
    /// What the header says: container, codec, duration, size, fps, keyframe spacing.
    #[serde(flatten)]
    pub info: vlmfuse_media::ClipInfo,
    /// Presentation times of the sampled frames, seconds.
    pub timestamps_s: Vec<f64>,
}

#[derive(Serialize)]
pub struct InferClipOut {
    #[serde(flatten)]
    pub fused: Fused,
    pub reporters: Ordered<ReporterOut>,
    /// Reporters left out of this round, with why.
    pub failed: Ordered<String>,
    pub clip: ClipOut,
    /// What the kinematic rules derived from the clip's `signals` track, with the evidence.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub derived: Option<vlmfuse_annotate::Annotation>,
    /// What the detector derived from the clip's frames (`[detect]`), with the evidence.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub detected: Option<vlmfuse_detect::DetectAnnotation>,
    /// Why the detector did not run on this clip (the round is stored without its labels).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub detect_error: Option<String>,
    pub timings_ms: Ordered<f64>,
}

#[derive(Serialize)]
pub struct InferBatchOut {
    pub clips: Vec<InferClipOut>,
}

pub fn state_out(eng: &Engine, rounds: u64) -> StateOut {
    let names = eng.reporters();
    let l = eng.ontology().len();
    StateOut {
        method: eng.method().name(),
        reputations: Ordered(
            names
                .iter()
                .cloned()
                .zip(eng.reputations().iter().copied())
                .collect(),
        ),
        labelled_rounds: eng.labelled(),
        threshold: eng.threshold().scalar(),
        thresholds: (eng.threshold().mode() == ThresholdMode::PerLabel).then(|| {
            Ordered(
                (0..l)
                    .map(|k| {
                        (
                            eng.ontology().id(k).to_string(),
                            eng.threshold().thresholds()[k],
                        )
                    })
                    .collect(),
            )
        }),
        reporters: Ordered(
            names
                .iter()
                .cloned()
                .zip(eng.stats().iter().cloned())
                .collect(),
        ),
        pool: eng.pool_sizes().map(|(labelled, unlabelled)| PoolOut {
            labelled,
            unlabelled,
            max_unlabelled: eng.config().adaptive.pool_max,
            approximate_knn: eng.approximate_knn(),
        }),
        rounds,
        state_seq: rounds + eng.labelled(),
        replica: None,
        dim: eng.dim(),
        serving: ServingOut {
            predictor: serving_predictor(eng),
            rule: eng.serving().map(|_| match eng.config().adaptive.serve {
                vlmfuse_fusion::Serve::Switch => "switch",
                vlmfuse_fusion::Serve::VoteFallback => "vote-fallback",
                vlmfuse_fusion::Serve::Model => "model",
            }),
            scores: eng.candidate_scores(),
        },
    }
}

/// What the labeler made of one text (`POST /v1/label`, `vlmfuse label --json`).
#[derive(Serialize)]
pub struct LabelOut {
    /// Label ids that are on, in ontology order.
    pub labels: Vec<String>,
    /// Every label's score, in ontology order (what it means depends on the labeler kind).
    pub scores: Ordered<f32>,
    /// Why each label is on, and the mentions that were read and discounted.
    pub evidence: Vec<vlmfuse_labeler::Evidence>,
}

impl From<vlmfuse_labeler::LabelerOutput> for LabelOut {
    fn from(o: vlmfuse_labeler::LabelerOutput) -> Self {
        LabelOut {
            labels: o.labels,
            scores: Ordered(o.scores.into_iter().map(|s| (s.id, s.score)).collect()),
            evidence: o.evidence,
        }
    }
}

/// `POST /v1/label` with one text.
#[derive(Serialize)]
pub struct LabelOneOut {
    pub labeler: String,
    pub label_ms: f64,
    #[serde(flatten)]
    pub result: LabelOut,
}

/// `POST /v1/label` with a list of texts: one result per text, in order.
#[derive(Serialize)]
pub struct LabelBatchOut {
    pub labeler: String,
    pub label_ms: f64,
    pub results: Vec<LabelOut>,
}
