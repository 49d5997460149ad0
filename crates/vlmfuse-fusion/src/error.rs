//! Errors of the fusion layer: every one is the caller's mistake except `Config`, which is the
//! operator's. The service maps them to HTTP statuses in one place.

use thiserror::Error;

#[derive(Debug, Error, Clone, PartialEq)]
pub enum FusionError {
    #[error("invalid fusion configuration: {0}")]
    Config(String),
    #[error("context has dimension {got}, but this engine uses dimension {expected}")]
    Dimension { expected: usize, got: usize },
    #[error("context is empty")]
    EmptyContext,
    #[error("context has a non-finite number at index {index}")]
    NonFinite { index: usize },
    #[error("context has zero length (norm 0) and cannot be normalised")]
    ZeroContext,
    #[error("reporter {0:?} is not configured")]
    UnknownReporter(String),
    #[error("a reporter has an empty name")]
    EmptyReporterName,
    #[error("label {label:?} in {whose} is not in the ontology")]
    UnknownLabel { label: String, whose: String },
    #[error("no reporter is present in the round (empty coalition)")]
    EmptyCoalition,
}

impl FusionError {
    /// Short machine-readable kind for API errors and metrics.
    pub fn kind(&self) -> &'static str {
        match self {
            FusionError::Config(_) => "config",
            FusionError::Dimension { .. } => "dimension_mismatch",
            FusionError::EmptyContext | FusionError::ZeroContext => "bad_context",
            FusionError::NonFinite { .. } => "non_finite",
            FusionError::UnknownReporter(_) | FusionError::EmptyReporterName => "unknown_reporter",
            FusionError::UnknownLabel { .. } => "unknown_label",
            FusionError::EmptyCoalition => "empty_coalition",
        }
    }
}
