//! Every number docs/PAPER-METHOD.md names is a field here rather than a constant in the code, so that the
//! service, `eval` and the tests all read the same defaults and a deployment can change them.

use crate::method::adaptive::AdaptiveConfig;
use serde::{Deserialize, Serialize};

/// Which fusion method the engine runs. `paper` is docs/PAPER-METHOD.md to the letter; `adaptive` is the
/// semi-supervised, calibrated, drift-aware method of docs/METHOD.md. Both keep the same rounds,
/// so a history made under one replays under the other.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Method {
    /// docs/PAPER-METHOD.md §1–7 exactly: labelled rounds only, reputation-weighted LLRs that sum to one.
    Paper,
    /// docs/METHOD.md: unlabelled rounds teach through a Dawid–Skene E-step, hierarchical
    /// reliabilities, Platt calibration, age decay and fixed-share reputations. The default: it
    /// meets issue 9's targets (no worse than majority vote from the first round, calibrated,
    /// drift-aware) where the paper method starts with every label on.
    #[default]
    Adaptive,
}

impl Method {
    pub const NAMES: [&'static str; 2] = ["paper", "adaptive"];

    pub fn name(&self) -> &'static str {
        match self {
            Method::Paper => "paper",
            Method::Adaptive => "adaptive",
        }
    }

    pub fn from_name(name: &str) -> Option<Self> {
        match name {
            "paper" => Some(Method::Paper),
            "adaptive" => Some(Method::Adaptive),
            _ => None,
        }
    }
}

impl std::fmt::Display for Method {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// Which parts of the method are switched off (PAPER-METHOD.md §6). All `false` is the full method.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Ablations {
    /// `w = 1/n` for ever: reputations never move.
    pub frozen_reputation: bool,
    /// `phi_i` is replaced by `v({i})`, the model's score alone, with no coalition baseline.
    pub per_model_score: bool,
    /// `rho = 0`: agreeing, error-correlated reports are counted in full.
    pub no_guardrail: bool,
    /// `kappa = 1` over the whole bank for `theta` and `pi`: one global notion of reliability.
    pub no_context: bool,
}

impl Ablations {
    /// The names `eval --ablation` takes, in the order tables print them.
    pub const NAMES: [&'static str; 4] = [
        "frozen-reputation",
        "per-model-score",
        "no-guardrail",
        "no-context",
    ];

    pub fn from_name(name: &str) -> Option<Self> {
        let mut a = Self::default();
        match name {
            "frozen-reputation" => a.frozen_reputation = true,
            "per-model-score" => a.per_model_score = true,
            "no-guardrail" => a.no_guardrail = true,
            "no-context" => a.no_context = true,
            _ => return None,
        }
        Some(a)
    }
}

/// How the decision threshold is fitted (PAPER-METHOD.md §3).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum ThresholdMode {
    /// One threshold for every label, maximising the mean per-round Jaccard index (the default).
    #[default]
    Global,
    /// One threshold per label, each maximising that label's Jaccard index TP/(TP+FP+FN).
    PerLabel,
}

/// The fusion's parameters. Field names follow docs/PAPER-METHOD.md's symbols.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct FusionConfig {
    /// Neighbours used for the reliabilities `theta` (PAPER-METHOD.md §2, `K`).
    pub k: usize,
    /// Kernel exponent `tau` in `max(0, cos)^tau`.
    pub tau: f64,
    /// Beta prior of the reliabilities.
    pub alpha0: f64,
    pub beta0: f64,
    /// Neighbours used for the contextual prior `pi` (`K_prior`).
    pub k_prior: usize,
    /// Beta prior of the contextual prior `pi` (PAPER-METHOD.md: Beta(1,1)).
    pub prior_alpha: f64,
    pub prior_beta: f64,
    /// Probability clip for every log (`eps`).
    pub eps: f64,
    /// Cap on the error correlation `rho`.
    pub rho_max: f64,
    /// Labelled rounds per reporter pair in the correlation window (`W`).
    pub corr_window: usize,
    /// Reputation learning rate `eta`.
    pub eta: f64,
    /// Payoff statistics: `u_i = phi_i + alpha * P * w_i / sum w`, `U_i = sum delta^(t-1) u_i`.
    pub payoff_alpha: f64,
    pub payoff_prize: f64,
    pub payoff_delta: f64,
    /// Labelled rounds whose inference-time posteriors the threshold is fitted on.
    pub threshold_window: usize,
    /// Labelled rounds before the threshold leaves its initial value.
    pub threshold_min_rounds: usize,
    /// The threshold used until `threshold_min_rounds` rounds are labelled.
    pub threshold_initial: f64,
    /// Grid step: thresholds are `step, 2 step, ...` strictly below 1.
    pub threshold_step: f64,
    /// Mean Jaccard scores closer than this tie, and a tie goes to the lowest threshold.
    pub threshold_tie: f64,
    pub threshold_mode: ThresholdMode,
    /// Exact Shapley values up to this many reporters in a round, sampled permutations above.
    pub shapley_exact_max: usize,
    /// Permutations drawn when sampling.
    pub shapley_samples: usize,
    /// Seed of the permutation sampler, mixed with the round's sequence number so that a replay
    /// draws the same permutations.
    pub shapley_seed: u64,
    /// Context dimension; `None` takes it from the first round the engine stores.
    pub dim: Option<usize>,
    pub ablations: Ablations,
    /// The fusion method (`paper` keeps docs/PAPER-METHOD.md exact; `adaptive` is docs/METHOD.md).
    pub method: Method,
    /// The `adaptive` method's parameters (ignored under `paper`).
    pub adaptive: AdaptiveConfig,
}

impl FusionConfig {
    /// The paper method's defaults with `method = "paper"`: docs/PAPER-METHOD.md to the letter.
    pub fn paper() -> Self {
        Self {
            method: Method::Paper,
            ..Self::default()
        }
    }
}

impl Default for FusionConfig {
    fn default() -> Self {
        Self {
            k: 50,
            tau: 4.0,
            alpha0: 1.0,
            beta0: 1.0,
            k_prior: 50,
            prior_alpha: 1.0,
            prior_beta: 1.0,
            eps: 1e-6,
            rho_max: 0.9,
            corr_window: 500,
            eta: 0.01,
            payoff_alpha: 0.0,
            payoff_prize: 0.0,
            payoff_delta: 1.0,
            threshold_window: 1000,
            threshold_min_rounds: 20,
            threshold_initial: 0.5,
            threshold_step: 0.005,
            threshold_tie: 1e-12,
            threshold_mode: ThresholdMode::Global,
            shapley_exact_max: 16,
            shapley_samples: 2000,
            shapley_seed: 0x5eed_f00d,
            dim: None,
            ablations: Ablations::default(),
            method: Method::default(),
            adaptive: AdaptiveConfig::default(),
        }
    }
}

impl FusionConfig {
    /// Rejects settings under which the formulas stop meaning anything, so that a bad config
    /// fails at start-up rather than as NaN posteriors later.
    pub fn validate(&self) -> Result<(), String> {
        let pos = |v: f64, name: &str| {
            if v.is_finite() && v > 0.0 {
                Ok(())
            } else {
                Err(format!("{name} must be a positive finite number, got {v}"))
            }
        };
        pos(self.tau, "tau")?;
        pos(self.alpha0, "alpha0")?;
        pos(self.beta0, "beta0")?;
        pos(self.prior_alpha, "prior_alpha")?;
        pos(self.prior_beta, "prior_beta")?;
        pos(self.threshold_step, "threshold_step")?;
        if !(self.eps > 0.0 && self.eps < 0.5) {
            return Err(format!("eps must lie in (0, 0.5), got {}", self.eps));
        }
        if !(0.0..1.0).contains(&self.rho_max) {
            return Err(format!("rho_max must lie in [0, 1), got {}", self.rho_max));
        }
        if !self.eta.is_finite() || self.eta < 0.0 {
            return Err(format!("eta must be finite and >= 0, got {}", self.eta));
        }
        if self.k == 0 || self.k_prior == 0 {
            return Err("k and k_prior must be at least 1".into());
        }
        if self.corr_window == 0 || self.threshold_window == 0 {
            return Err("corr_window and threshold_window must be at least 1".into());
        }
        if self.threshold_step >= 1.0 {
            return Err("threshold_step must be below 1".into());
        }
        if !(0.0..=1.0).contains(&self.threshold_initial) {
            return Err("threshold_initial must lie in [0, 1]".into());
        }
        if self.shapley_exact_max > 20 {
            return Err("shapley_exact_max above 20 would enumerate millions of coalitions".into());
        }
        if self.shapley_samples == 0 {
            return Err("shapley_samples must be at least 1".into());
        }
        if self.dim == Some(0) {
            return Err("dim must be at least 1".into());
        }
        for v in [self.payoff_alpha, self.payoff_prize, self.payoff_delta] {
            if !v.is_finite() {
                return Err("payoff parameters must be finite".into());
            }
        }
        self.adaptive
            .validate()
            .map_err(|e| format!("adaptive.{e}"))?;
        Ok(())
    }

    /// The threshold grid `step, 2 step, ...` below 1, each point the double nearest the decimal
    /// (`g / (1/step)` rather than a running sum, which would drift by an ulp a step).
    pub fn threshold_grid(&self) -> Vec<f64> {
        let per_unit = (1.0 / self.threshold_step).round();
        let exact = (per_unit * self.threshold_step - 1.0).abs() < 1e-9;
        let mut grid = Vec::new();
        let mut g = 1u32;
        loop {
            let t = if exact {
                g as f64 / per_unit
            } else {
                g as f64 * self.threshold_step
            };
            if t >= 1.0 - 1e-12 {
                break;
            }
            grid.push(t);
            g += 1;
        }
        grid
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn grid_is_the_specs_199_points() {
        let g = FusionConfig::default().threshold_grid();
        assert_eq!(g.len(), 199);
        assert_eq!(g[0], 0.005);
        assert_eq!(g[1], 0.01);
        assert_eq!(g[198], 0.995);
        assert_eq!(g[99], 0.5);
    }

    #[test]
    fn defaults_validate_and_nonsense_does_not() {
        assert!(FusionConfig::default().validate().is_ok());
        let bad = FusionConfig {
            eps: 0.0,
            ..Default::default()
        };
        assert!(bad.validate().is_err());
        let bad = FusionConfig {
            tau: f64::NAN,
            ..Default::default()
        };
        assert!(bad.validate().is_err());
    }
}
