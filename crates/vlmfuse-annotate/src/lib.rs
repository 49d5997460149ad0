//! Kinematic driving labels: `brake`, `accelerate`, `stop`, `turn_left`, `turn_right` and
//! `merge` derived from a vehicle-signal track (speed, acceleration, steering, yaw rate,
//! pedals, turn signal), the paper's "kinematic" annotation component.
//!
//! Why a separate annotator: the vision-language models label what a clip *looks* like; the
//! vehicle's own recordings say what the car *did*. Where the signals are decisive that is as
//! close to ground truth as a driving dataset gets, and its errors are independent of the
//! models'. The rules ([`rules`]) therefore abstain rather than guess: a label the signals
//! cannot decide is reported undecided, with the reason.
//!
//! No I/O: [`Track::parse`] takes bytes the caller read (and bounded). [`sim`] simulates
//! labelled tracks for scripted manoeuvres and scores the rules on them ([`sim::evaluate`]).

pub mod config;
pub mod rules;
mod signal;
pub mod sim;
pub mod track;

pub use config::AnnotateConfig;
pub use rules::{annotate, confidence, Annotation, Derived, Evidence, Undecided, LABELS};
pub use track::{Columns, Track, TrackError, TrackLimits, TurnSignal, COLUMNS};
