//! Helpers shared by the fusion test files: a tiny deterministic generator and a builder for
//! SPEC §8 records.

#![allow(dead_code)]

use std::collections::BTreeMap;
use vlmfuse_fusion::RoundRecord;

/// A 64-bit LCG: deterministic test data without a dependency.
pub struct Lcg(pub u64);

impl Lcg {
    /// Uniform in [0, 1).
    pub fn f(&mut self) -> f64 {
        self.0 = self
            .0
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (self.0 >> 11) as f64 / (1u64 << 53) as f64
    }
}

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
