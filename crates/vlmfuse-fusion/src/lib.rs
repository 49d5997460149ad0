//! The fusion method of SPEC.md §1–7, with no I/O: Shapley-credited, context-aware
//! Dawid–Skene with an agreement guardrail. Everything here is deterministic and serialisable;
//! the service persists it and `eval` replays it.

pub mod adaptive;
pub mod bank;
pub mod bench;
pub mod config;
pub mod corr;
pub mod curve;
pub mod engine;
pub mod error;
pub mod metrics;
pub mod ontology;
pub mod replay;
pub mod signals;
pub mod threshold;

pub use adaptive::{AdaptiveConfig, Guardrail, Reputation, SoftTruth, WeightNorm};
pub use config::{Ablations, FusionConfig, Method, ThresholdMode};
pub use engine::{
    fixed_share, reputation_update, Engine, FeedbackOutcome, Inference, LabelExplanation,
    LabelledRound, ReporterStats, Round, RoundRecord,
};
pub use error::FusionError;
pub use ontology::{Label, Ontology};
pub use signals::{Credit, ShapleyMethod, Signals};
