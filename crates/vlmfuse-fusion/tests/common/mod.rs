//! Helpers shared by the fusion test files: the test kit's generator and a builder for docs/PAPER-METHOD.md §8
//! records.

#![allow(dead_code)]

use std::collections::BTreeMap;
use vlmfuse_fusion::RoundRecord;
#[allow(unused_imports)]
pub use vlmfuse_testkit::rng::Lcg;

/// A record with the given context, reports `(reporter, labels)` and optional truth.
pub fn record(ctx: Vec<f64>, reports: &[(&str, &[&str])], truth: Option<&[&str]>) -> RoundRecord {
    RoundRecord {
        id: None,
        context: ctx,
        reports: reports
            .iter()
            .map(|(n, l)| (n.to_string(), l.iter().map(|s| s.to_string()).collect()))
            .collect::<BTreeMap<_, _>>(),
        truth: truth.map(|t| t.iter().map(|s| s.to_string()).collect()),
    }
}
