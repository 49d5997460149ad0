//! Labels from the vehicle's signals (`signals` tracks) for the service: parse and check a track
//! under `[annotate]`'s bounds, check that it covers its clip, run the kinematic rules, and turn
//! their decisions into a partial feedback's truth (source `kinematics`).

use super::ServiceError;
use crate::config::AnnotateSection;
use vlmfuse_annotate::{annotate, Annotation, Track};
use vlmfuse_fusion::{Ontology, UNKNOWN};

/// The source name of derived-from-signals feedback.
pub const KINEMATICS: &str = "kinematics";

/// Parses a track (CSV or JSON lines) under `[annotate]`'s bounds: a 4xx naming the problem
/// (line, column, kind) for anything the rules cannot trust.
pub fn parse_track(cfg: &AnnotateSection, bytes: &[u8]) -> Result<Track, ServiceError> {
    if bytes.len() as u64 > cfg.max_bytes {
        return Err(ServiceError::SignalsTooLarge(cfg.max_bytes));
    }
    Track::parse_with(bytes, &cfg.limits()).map_err(|e| ServiceError::Signals {
        kind: e.kind(),
        message: format!("signals: {e}"),
    })
}

/// The rules on a track, which must cover `[0, duration_s]` (when the clip's duration is known)
/// within `cover_tolerance_s`.
pub fn derive(
    cfg: &AnnotateSection,
    track: &Track,
    duration_s: Option<f64>,
) -> Result<Annotation, ServiceError> {
    if let Some(d) = duration_s {
        track
            .covers_duration(d, cfg.cover_tolerance_s)
            .map_err(|e| ServiceError::Signals {
                kind: e.kind(),
                message: format!("signals: {e}"),
            })?;
    }
    let window = duration_s.map(|d| (0.0, d));
    Ok(annotate(track, window, &cfg.rules))
}

/// The truth a derived annotation gives: 0/1 for each decided label the ontology has,
/// `UNKNOWN` elsewhere. `None` when it decides nothing.
pub fn truth_of(ontology: &Ontology, a: &Annotation) -> Option<Vec<u8>> {
    let mut y = vec![UNKNOWN; ontology.len()];
    for d in &a.labels {
        if let Some(k) = ontology.lookup(&d.label) {
            y[k] = d.value as u8;
        }
    }
    y.iter().any(|&v| v <= 1).then_some(y)
}
