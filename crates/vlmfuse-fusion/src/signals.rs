//! What a round computed at inference time, and everything derived from it afterwards.
//!
//! docs/PAPER-METHOD.md §5 credits a model "for what it contributed when it spoke": feedback may arrive much
//! later, when the bank and the correlations have moved on. So inference freezes the reliabilities,
//! correlations, prior, reports and weights of the coalition in a [`Signals`], and the posterior,
//! every coalition's value and the Shapley credit are pure functions of it.

use rand::seq::SliceRandom;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

/// A round's frozen inputs, over the `p` reporters present (the coalition), in reporter order.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Signals {
    /// Number of labels.
    pub l: usize,
    /// Reporter indices present, ascending.
    pub coalition: Vec<usize>,
    /// `theta+` per member and label, `p * L`, unclipped.
    pub theta_pos: Vec<f64>,
    /// `theta-` per member and label, `p * L`, unclipped.
    pub theta_neg: Vec<f64>,
    /// `rho` per member pair and label, `p * p * L` (symmetric, zero diagonal).
    pub rho: Vec<f64>,
    /// Contextual prior per label, unclipped.
    pub prior: Vec<f64>,
    /// Reports per member and label, `p * L`.
    pub reports: Vec<u8>,
    /// Reputation of each member as used for this round.
    pub w: Vec<f64>,
    /// Probability clip.
    pub eps: f64,
}

/// How a round's Shapley values were obtained.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "method", rename_all = "snake_case")]
pub enum ShapleyMethod {
    Exact,
    /// Monte-Carlo over random permutations; `std_error` is the standard error of each member's
    /// mean marginal contribution (same order as the coalition).
    Sampled {
        samples: usize,
        std_error: Vec<f64>,
    },
    /// The `per-model-score` ablation: `v({i})`, not a Shapley value.
    PerModelScore,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Credit {
    /// Credit per coalition member, coalition order.
    pub phi: Vec<f64>,
    /// `v(N)`: the grand coalition's log-score gain over the prior.
    pub v_full: f64,
    pub method: ShapleyMethod,
}

impl Credit {
    /// The credit per configured reporter (`n` of them): each coalition member's at its
    /// reporter's index, 0 for the absent.
    pub fn by_reporter(&self, coalition: &[usize], n: usize) -> Vec<f64> {
        let mut phi = vec![0.0; n];
        for (a, &i) in coalition.iter().enumerate() {
            phi[i] = self.phi[a];
        }
        phi
    }
}

#[inline]
pub fn clip(p: f64, eps: f64) -> f64 {
    p.clamp(eps, 1.0 - eps)
}

/// Logistic sigmoid, evaluated on the side that does not overflow: `1 / (1 + e^-z)` for
/// `z >= 0`, `e^z / (1 + e^z)` below. Written as one `exp(-|z|)` and a select of the
/// numerator, which gives those two expressions' bits exactly, without a branch on the sign:
/// the calibration's refits take the sigmoid of thousands of logits of either sign per pass,
/// and a mispredicted branch cost more than the `exp`.
#[inline]
pub fn sigmoid(z: f64) -> f64 {
    let e = (-z.abs()).exp();
    let num = if z >= 0.0 { 1.0 } else { e };
    num / (1.0 + e)
}

/// Log score `y log q + (1-y) log(1-q)` of a clipped probability.
#[inline]
pub fn log_score(q: f64, y: u8, eps: f64) -> f64 {
    let q = clip(q, eps);
    if y != 0 {
        q.ln()
    } else {
        (1.0 - q).ln()
    }
}

impl Signals {
    pub fn members(&self) -> usize {
        self.coalition.len()
    }

    /// `lambda_ik` for every member and label (PAPER-METHOD.md §3), from clipped reliabilities.
    pub fn llr(&self) -> Vec<f64> {
        let eps = self.eps;
        self.reports
            .iter()
            .enumerate()
            .map(|(idx, &r)| {
                let tp = clip(self.theta_pos[idx], eps);
                let tn = clip(self.theta_neg[idx], eps);
                if r != 0 {
                    (tp / tn).ln()
                } else {
                    ((1.0 - tp) / (1.0 - tn)).ln()
                }
            })
            .collect()
    }

    /// `logit(pi_k)` of the clipped prior.
    pub fn prior_logit(&self) -> Vec<f64> {
        self.prior
            .iter()
            .map(|&p| {
                let p = clip(p, self.eps);
                (p / (1.0 - p)).ln()
            })
            .collect()
    }

    #[inline]
    fn rho(&self, a: usize, b: usize, k: usize) -> f64 {
        let p = self.members();
        self.rho[(a * p + b) * self.l + k]
    }

    /// The guardrail denominator `1 + sum_{j in C, j != i} rho_ijk 1{r_jk == r_ik}`.
    fn guard(&self, a: usize, k: usize, in_c: &dyn Fn(usize) -> bool) -> f64 {
        let l = self.l;
        let mut d = 1.0;
        for b in 0..self.members() {
            if b != a && in_c(b) && self.reports[b * l + k] == self.reports[a * l + k] {
                d += self.rho(a, b, k);
            }
        }
        d
    }

    /// Each member's weighted, guardrailed LLR `w_i * lambda~_ik` within coalition `in_c`,
    /// `p * L` (zero for members outside it).
    pub fn contributions(&self, lam: &[f64], in_c: &dyn Fn(usize) -> bool) -> Vec<f64> {
        let l = self.l;
        let mut out = vec![0.0; self.members() * l];
        for a in 0..self.members() {
            if !in_c(a) {
                continue;
            }
            for k in 0..l {
                out[a * l + k] = self.w[a] * lam[a * l + k] / self.guard(a, k, in_c);
            }
        }
        out
    }

    /// The coalition posterior `q^(C)` per label, clipped (PAPER-METHOD.md §4). The empty coalition gives
    /// the prior itself (clipped), not `sigmoid(logit(pi))`, which could differ by an ulp.
    pub fn posterior(
        &self,
        lam: &[f64],
        logit_pi: &[f64],
        in_c: &dyn Fn(usize) -> bool,
    ) -> Vec<f64> {
        let l = self.l;
        if !(0..self.members()).any(in_c) {
            return self.prior.iter().map(|&p| clip(p, self.eps)).collect();
        }
        let c = self.contributions(lam, in_c);
        (0..l)
            .map(|k| {
                let mut z = logit_pi[k];
                for a in 0..self.members() {
                    if in_c(a) {
                        z += c[a * l + k];
                    }
                }
                clip(sigmoid(z), self.eps)
            })
            .collect()
    }

    /// The grand coalition's evidence `sum_i w_i lambda~_ik` per label: the fused logit less the
    /// prior's log-odds. The `adaptive` method calibrates the two separately.
    pub fn evidence(&self) -> Vec<f64> {
        let l = self.l;
        let lam = self.llr();
        let c = self.contributions(&lam, &|_| true);
        let mut e = vec![0.0; l];
        for a in 0..self.members() {
            for k in 0..l {
                e[k] += c[a * l + k];
            }
        }
        e
    }

    /// The grand coalition's fused logit `logit(pi_k) + sum_i w_i lambda~_ik` per label, before
    /// the sigmoid and the clip.
    pub fn fused_logit(&self) -> Vec<f64> {
        let l = self.l;
        let lam = self.llr();
        let mut z = self.prior_logit();
        let c = self.contributions(&lam, &|_| true);
        for a in 0..self.members() {
            for k in 0..l {
                z[k] += c[a * l + k];
            }
        }
        z
    }

    /// The grand coalition's posterior: what the round predicts.
    pub fn full_posterior(&self) -> Vec<f64> {
        self.posterior(&self.llr(), &self.prior_logit(), &|_| true)
    }

    /// The prior's score over the labels whose truth is known (`y_k` is 0 or 1; a label marked
    /// [`crate::UNKNOWN`] is left out of every value, so partial feedback credits only what it
    /// says).
    fn prior_score(&self, y: &[u8]) -> f64 {
        self.prior
            .iter()
            .zip(y)
            .filter(|(_, &yk)| yk <= 1)
            .map(|(&p, &yk)| log_score(p, yk, self.eps))
            .sum()
    }

    /// `v(C) = sum_k s(q^(C)_k) - sum_k s(pi_k)`.
    pub fn value(
        &self,
        lam: &[f64],
        logit_pi: &[f64],
        y: &[u8],
        in_c: &dyn Fn(usize) -> bool,
    ) -> f64 {
        if !(0..self.members()).any(in_c) {
            return 0.0;
        }
        let q = self.posterior(lam, logit_pi, in_c);
        let s: f64 = q
            .iter()
            .zip(y)
            .filter(|(_, &yk)| yk <= 1)
            .map(|(&p, &yk)| log_score(p, yk, self.eps))
            .sum();
        s - self.prior_score(y)
    }

    /// `v(C)` for every subset of the coalition, indexed by bit mask (members in coalition order).
    pub fn all_values(&self, y: &[u8]) -> Vec<f64> {
        let p = self.members();
        let lam = self.llr();
        let lp = self.prior_logit();
        (0..1usize << p)
            .map(|mask| self.value(&lam, &lp, y, &|a| mask >> a & 1 == 1))
            .collect()
    }

    /// The round's credit as the configuration asks for it (PAPER-METHOD.md §4): exact Shapley
    /// values up to `shapley_exact_max` members, sampled ones (seeded by the round's `seq`)
    /// beyond, per-model scores under that ablation.
    pub fn credit(&self, cfg: &crate::config::FusionConfig, y: &[u8], seq: u64) -> Credit {
        if cfg.ablations.per_model_score {
            self.per_model_score(y)
        } else if self.members() <= cfg.shapley_exact_max {
            self.shapley_exact(y)
        } else {
            let seed = cfg.shapley_seed ^ seq.wrapping_mul(0x9e37_79b9_7f4a_7c15);
            self.shapley_sampled(y, cfg.shapley_samples, seed)
        }
    }

    /// Exact Shapley values by enumerating all `2^p` coalitions.
    pub fn shapley_exact(&self, y: &[u8]) -> Credit {
        let p = self.members();
        let v = self.all_values(y);
        // |C|! (p-|C|-1)! / p!  ==  1 / (p * binom(p-1, |C|)).
        let mut weight = vec![0.0; p.max(1)];
        for (s, w) in weight.iter_mut().enumerate().take(p) {
            let mut binom = 1.0f64;
            for t in 0..s {
                binom = binom * (p - 1 - t) as f64 / (t + 1) as f64;
            }
            *w = 1.0 / (p as f64 * binom);
        }
        let mut phi = vec![0.0; p];
        for (a, phi_a) in phi.iter_mut().enumerate() {
            let bit = 1usize << a;
            let mut acc = 0.0;
            for mask in 0..1usize << p {
                if mask & bit == 0 {
                    acc += weight[mask.count_ones() as usize] * (v[mask | bit] - v[mask]);
                }
            }
            *phi_a = acc;
        }
        Credit {
            phi,
            v_full: v[(1usize << p) - 1],
            method: ShapleyMethod::Exact,
        }
    }

    /// Shapley values estimated over `samples` random permutations. Each permutation's marginal
    /// contributions telescope to `v(N)`, so efficiency holds exactly for the estimate too.
    pub fn shapley_sampled(&self, y: &[u8], samples: usize, seed: u64) -> Credit {
        let p = self.members();
        let l = self.l;
        let lam = self.llr();
        let lp = self.prior_logit();
        let base = self.prior_score(y);
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut order: Vec<usize> = (0..p).collect();
        let mut sum = vec![0.0; p];
        let mut sumsq = vec![0.0; p];
        let mut inside = vec![false; p];
        // Guardrail denominators of the members inside, per label, updated as members join.
        let mut den = vec![1.0; p * l];
        let mut v_full = 0.0;
        for _ in 0..samples {
            order.shuffle(&mut rng);
            inside.iter_mut().for_each(|b| *b = false);
            den.iter_mut().for_each(|d| *d = 1.0);
            let mut prev = 0.0;
            for &m in &order {
                for a in 0..p {
                    if inside[a] {
                        for k in 0..l {
                            if self.reports[a * l + k] == self.reports[m * l + k] {
                                let r = self.rho(a, m, k);
                                den[a * l + k] += r;
                                den[m * l + k] += r;
                            }
                        }
                    }
                }
                inside[m] = true;
                let mut score = 0.0;
                for k in 0..l {
                    if y[k] > 1 {
                        continue;
                    }
                    let mut z = lp[k];
                    for a in 0..p {
                        if inside[a] {
                            z += self.w[a] * lam[a * l + k] / den[a * l + k];
                        }
                    }
                    score += log_score(clip(sigmoid(z), self.eps), y[k], self.eps);
                }
                let v = score - base;
                let marginal = v - prev;
                sum[m] += marginal;
                sumsq[m] += marginal * marginal;
                prev = v;
            }
            v_full = prev;
        }
        let n = samples as f64;
        let phi: Vec<f64> = sum.iter().map(|s| s / n).collect();
        let std_error = (0..p)
            .map(|a| {
                if samples < 2 {
                    f64::INFINITY
                } else {
                    let var = (sumsq[a] - sum[a] * sum[a] / n) / (n - 1.0);
                    (var.max(0.0) / n).sqrt()
                }
            })
            .collect();
        Credit {
            phi,
            v_full,
            method: ShapleyMethod::Sampled { samples, std_error },
        }
    }

    /// The `per-model-score` ablation: each member's value alone, `v({i})`.
    pub fn per_model_score(&self, y: &[u8]) -> Credit {
        let lam = self.llr();
        let lp = self.prior_logit();
        let phi = (0..self.members())
            .map(|a| self.value(&lam, &lp, y, &|b| b == a))
            .collect();
        Credit {
            phi,
            v_full: self.value(&lam, &lp, y, &|_| true),
            method: ShapleyMethod::PerModelScore,
        }
    }
}

#[cfg(test)]
mod sigmoid_tests {
    use super::sigmoid;

    #[test]
    fn the_branch_free_sigmoid_is_the_two_sided_one_bit_for_bit() {
        let two_sided = |z: f64| {
            if z >= 0.0 {
                1.0 / (1.0 + (-z).exp())
            } else {
                let e = z.exp();
                e / (1.0 + e)
            }
        };
        let mut z = -800.0f64;
        while z <= 800.0 {
            for v in [z, z + 1e-9, -z * 1e-3, z * 0.37] {
                assert_eq!(sigmoid(v).to_bits(), two_sided(v).to_bits(), "{v}");
            }
            z += 0.173;
        }
        for v in [
            0.0,
            -0.0,
            f64::MIN_POSITIVE,
            -f64::MIN_POSITIVE,
            1e300,
            -1e300,
        ] {
            assert_eq!(sigmoid(v).to_bits(), two_sided(v).to_bits(), "{v}");
        }
        assert!(sigmoid(f64::NAN).is_nan());
        assert_eq!(sigmoid(f64::INFINITY), 1.0);
        assert_eq!(sigmoid(f64::NEG_INFINITY), 0.0);
    }
}
