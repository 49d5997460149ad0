//! The fusion method of docs/PAPER-METHOD.md §1–7, with no I/O: Shapley-credited, context-aware
//! Dawid–Skene with an agreement guardrail, and the `adaptive` method of docs/METHOD.md.
//! Everything here is deterministic: the engine is a pure function of its events, so the
//! service persists the events and rebuilds the engine by replaying them ([`replay`]), as `eval`
//! does over a rounds file.

pub mod bank;
pub mod bench;
pub mod beside;
pub mod config;
pub mod corr;
pub mod curve;
pub mod engine;
pub mod error;
mod method;
pub mod metrics;
pub mod ontology;
pub mod replay;
pub mod reputation;
pub mod review;
pub mod signals;
mod sorted_map;
pub mod threshold;

pub use beside::Beside;
pub use config::{Ablations, FusionConfig, Method, ThresholdMode};
pub use engine::{
    Engine, FeedbackOutcome, Inference, LabelExplanation, LabelledRound, ReporterStats, Round,
    RoundRecord, ENGINE_LAYOUT, UNKNOWN,
};
pub use error::FusionError;
pub use method::adaptive::{
    AdaptiveConfig, CandidateScore, Guardrail, Predictor, Reputation, Scan, Serve, SoftTruth,
    WeightNorm,
};
pub use ontology::{Label, Ontology};
/// docs/PAPER-METHOD.md §5's multiplicative update, [`reputation::multiplicative`].
pub use reputation::{fixed_share, multiplicative as reputation_update};
pub use signals::{Credit, ShapleyMethod, Signals};
