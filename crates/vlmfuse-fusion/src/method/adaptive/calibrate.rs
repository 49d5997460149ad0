//! Per-label calibration of the fused logit (docs/METHOD.md §5): Platt scaling with the
//! contextual prior and the reporters' evidence as two separate inputs.
//!
//! The fused logit is `z = p + e`, the prior's log-odds `p = logit(pi_k)` plus the evidence
//! `e = sum_i w_i lambda~_ik`. Label `k` maps it to `sigmoid(a_k e + c_k p + b_k)`: Platt scaling
//! (`a = c`) would only stretch `z`, but when reporters' errors are correlated in ways the
//! guardrail misses, the evidence is over-counted relative to the prior, and only a separate
//! slope for each can undo that. The identity is `(a, c, b) = (1, 1, 0)`.
//!
//! The parameters are the maximum a posteriori fit over the inference-time inputs of the last
//! `calib_window` labelled rounds, with a Gaussian prior that ties each label to a pooled fit over
//! all labels, which is in turn tied to the identity. So with no labels the map is the identity,
//! with a few it is one shared map (fourteen times the data of one label), and only a label with
//! enough rounds of its own moves away from the pool: rare labels never get a wild map.
//!
//! Refits are warm-started Newton steps on a strictly convex objective (the priors make the
//! Hessian positive definite), so a refit after each labelled round costs a pass over the window
//! per step, and its result depends only on the rounds pushed, in order.

use crate::signals::sigmoid;
use std::collections::VecDeque;

/// Inputs are clipped to this magnitude before they enter a fit: beyond it the sigmoid is 0 or 1
/// to double precision, and a huge input would only destabilise Newton's steps.
pub const LOGIT_CLIP: f64 = 30.0;

/// `(a, c, b)`: slope of the evidence, slope of the prior log-odds, intercept.
pub type Params = [f64; 3];

const IDENTITY: Params = [1.0, 1.0, 0.0];

#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Calibrator {
    l: usize,
    window: usize,
    label_prior: f64,
    pooled_prior: f64,
    steps: usize,
    min_slope: f64,
    /// The window: per labelled round, `(evidence, prior log-odds)` per label and the truth.
    rounds: VecDeque<(Vec<[f64; 2]>, Vec<u8>)>,
    pooled: Params,
    per_label: Vec<Params>,
    /// Refit after every `every`-th round taken in (1: each; see [`Calibrator::refit_every`]).
    #[serde(default = "one")]
    every: usize,
    /// Rounds taken in.
    #[serde(default)]
    pushed: u64,
}

fn one() -> usize {
    1
}

/// Gradient and Hessian of the negative log-likelihood of `sigmoid(a e + c p + b)`.
#[derive(Default, Clone, Copy)]
struct Acc {
    g: [f64; 3],
    h: [[f64; 3]; 3],
}

impl Acc {
    #[inline]
    fn add(&mut self, th: &Params, x: [f64; 2], y: u8) {
        let f = [x[0], x[1], 1.0];
        let p = sigmoid(th[0] * f[0] + th[1] * f[1] + th[2]);
        let r = p - y as f64;
        let w = p * (1.0 - p);
        for i in 0..3 {
            self.g[i] += r * f[i];
            for j in 0..3 {
                self.h[i][j] += w * f[i] * f[j];
            }
        }
    }

    /// One damped Newton step for the objective plus `lambda/2 |theta - centre|^2`.
    fn step(&self, th: Params, centre: Params, lambda: f64) -> Params {
        let mut g = self.g;
        let mut h = self.h;
        for i in 0..3 {
            g[i] += lambda * (th[i] - centre[i]);
            h[i][i] += lambda;
        }
        let Some(d) = solve3(h, g) else {
            return th;
        };
        let norm = d.iter().map(|v| v * v).sum::<f64>().sqrt();
        // Far from the optimum a full Newton step on a logistic loss can overshoot; the bound is
        // loose enough never to bind near it.
        let s = if norm > 4.0 { 4.0 / norm } else { 1.0 };
        [th[0] - s * d[0], th[1] - s * d[1], th[2] - s * d[2]]
    }
}

/// Solves `h x = g` for a symmetric positive definite 3x3 `h` (Cholesky).
// Index loops are the textbook form of the factorisation and easier to check against it.
#[allow(clippy::needless_range_loop)]
fn solve3(h: [[f64; 3]; 3], g: [f64; 3]) -> Option<[f64; 3]> {
    let mut l = [[0.0f64; 3]; 3];
    for i in 0..3 {
        for j in 0..=i {
            let mut s = h[i][j];
            for k in 0..j {
                s -= l[i][k] * l[j][k];
            }
            if i == j {
                if !(s > 0.0 && s.is_finite()) {
                    return None;
                }
                l[i][i] = s.sqrt();
            } else {
                l[i][j] = s / l[j][j];
            }
        }
    }
    let mut y = [0.0; 3];
    for i in 0..3 {
        let mut s = g[i];
        for k in 0..i {
            s -= l[i][k] * y[k];
        }
        y[i] = s / l[i][i];
    }
    let mut x = [0.0; 3];
    for i in (0..3).rev() {
        let mut s = y[i];
        for k in i + 1..3 {
            s -= l[k][i] * x[k];
        }
        x[i] = s / l[i][i];
    }
    x.iter().all(|v| v.is_finite()).then_some(x)
}

fn clip_input(v: f64) -> f64 {
    if v.is_nan() {
        0.0
    } else {
        v.clamp(-LOGIT_CLIP, LOGIT_CLIP)
    }
}

impl Calibrator {
    pub fn new(
        l: usize,
        window: usize,
        label_prior: f64,
        pooled_prior: f64,
        steps: usize,
        min_slope: f64,
    ) -> Self {
        Self {
            l,
            window,
            label_prior,
            pooled_prior,
            steps,
            min_slope,
            rounds: VecDeque::new(),
            pooled: IDENTITY,
            per_label: vec![IDENTITY; l],
            every: 1,
            pushed: 0,
        }
    }

    /// Refits after every `n`-th labelled round only (each refit passes over the whole window:
    /// where the calibration is one of several it costs as much as the rest of a round).
    pub fn refit_every(mut self, n: usize) -> Self {
        self.every = n.max(1);
        self
    }

    /// The calibrated probability of label `k` for evidence `e` and prior log-odds `p`.
    #[inline]
    pub fn apply(&self, k: usize, e: f64, p: f64) -> f64 {
        let th = self.per_label[k];
        sigmoid(th[0] * clip_input(e) + th[1] * clip_input(p) + th[2])
    }

    /// Takes in a labelled round's inference-time evidence and prior log-odds, and refits.
    pub fn push(&mut self, evidence: &[f64], prior_logit: &[f64], y: &[u8]) {
        debug_assert_eq!(evidence.len(), self.l);
        let x: Vec<[f64; 2]> = evidence
            .iter()
            .zip(prior_logit)
            .map(|(&e, &p)| [clip_input(e), clip_input(p)])
            .collect();
        self.rounds.push_back((x, y.to_vec()));
        if self.rounds.len() > self.window {
            self.rounds.pop_front();
        }
        self.pushed += 1;
        // Every round while the window fills (a fit on few rounds moves a lot per round), then
        // every `every`-th.
        if self.pushed <= self.window as u64 || self.pushed.is_multiple_of(self.every as u64) {
            self.refit();
        }
    }

    fn clamp(&self, th: Params) -> Params {
        [th[0].max(self.min_slope), th[1].max(self.min_slope), th[2]]
    }

    fn refit(&mut self) {
        for _ in 0..self.steps {
            let mut acc = Acc::default();
            for (x, y) in &self.rounds {
                // Labels of unknown truth (partial feedback) fit nothing.
                for k in (0..self.l).filter(|&k| y[k] <= 1) {
                    acc.add(&self.pooled, x[k], y[k]);
                }
            }
            self.pooled = self.clamp(acc.step(self.pooled, IDENTITY, self.pooled_prior));
        }
        let centre = self.pooled;
        for k in 0..self.l {
            let mut th = self.per_label[k];
            for _ in 0..self.steps {
                let mut acc = Acc::default();
                for (x, y) in self.rounds.iter().filter(|(_, y)| y[k] <= 1) {
                    acc.add(&th, x[k], y[k]);
                }
                th = self.clamp(acc.step(th, centre, self.label_prior));
            }
            self.per_label[k] = th;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    impl Calibrator {
        /// Rounds in the window.
        fn len(&self) -> usize {
            self.rounds.len()
        }

        /// `(a, c, b)` of label `k`.
        fn params(&self, k: usize) -> Params {
            self.per_label[k]
        }
    }

    fn lcg(s: &mut u64) -> f64 {
        *s = s
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (*s >> 11) as f64 / (1u64 << 53) as f64
    }

    #[test]
    fn solve3_solves() {
        let h = [[4.0, 1.0, 0.5], [1.0, 3.0, 0.2], [0.5, 0.2, 2.0]];
        let x = [1.0, -2.0, 0.5];
        let g: Vec<f64> = (0..3)
            .map(|i| (0..3).map(|j| h[i][j] * x[j]).sum())
            .collect();
        let got = solve3(h, [g[0], g[1], g[2]]).unwrap();
        for i in 0..3 {
            assert!((got[i] - x[i]).abs() < 1e-12);
        }
        assert!(solve3([[0.0; 3]; 3], [1.0, 0.0, 0.0]).is_none());
    }

    #[test]
    fn refitting_every_third_round_once_the_window_is_full() {
        // A window of 2: rounds 1 and 2 refit (the window fills), then only every third.
        let mut every = Calibrator::new(1, 2, 1.0, 1.0, 1, 0.05).refit_every(3);
        let mut each = Calibrator::new(1, 2, 1.0, 1.0, 1, 0.05);
        let data = [(2.0, 0u8), (1.5, 0), (2.5, 0), (3.0, 0), (2.0, 0), (2.7, 0)];
        let mut last = every.apply(0, 1.0, 0.0);
        for (i, (e, y)) in data.into_iter().enumerate() {
            every.push(&[e], &[0.0], &[y]);
            each.push(&[e], &[0.0], &[y]);
            let now = every.apply(0, 1.0, 0.0);
            let round = i + 1;
            if round <= 2 || round % 3 == 0 {
                assert_ne!(now, last, "not refitted after round {round}");
                if round <= 3 {
                    // Refitted as often as the every-round calibrator so far: the same map.
                    assert_eq!(now, each.apply(0, 1.0, 0.0), "round {round}");
                }
            } else {
                assert_eq!(now, last, "refitted after round {round}");
            }
            last = now;
        }
    }

    #[test]
    fn identity_until_data_and_then_the_true_map() {
        let mut c = Calibrator::new(2, 3000, 1.0, 1.0, 3, 0.05);
        assert_eq!(c.apply(0, 0.7, -0.2), sigmoid(0.5));
        // Truth from sigmoid(0.5 e + 1.5 p - 0.5) for label 0 (evidence over-counted) and
        // sigmoid(2 e + 1 p) for label 1 (under-confident).
        let mut s = 11u64;
        for _ in 0..3000 {
            let e = [4.0 * lcg(&mut s) - 2.0, 4.0 * lcg(&mut s) - 2.0];
            let p = [2.0 * lcg(&mut s) - 1.5, 2.0 * lcg(&mut s) - 1.5];
            let y = [
                (lcg(&mut s) < sigmoid(0.5 * e[0] + 1.5 * p[0] - 0.5)) as u8,
                (lcg(&mut s) < sigmoid(2.0 * e[1] + p[1])) as u8,
            ];
            c.push(&e, &p, &y);
        }
        let t0 = c.params(0);
        let t1 = c.params(1);
        assert!((t0[0] - 0.5).abs() < 0.15, "{t0:?}");
        assert!((t0[1] - 1.5).abs() < 0.35, "{t0:?}");
        assert!((t0[2] + 0.5).abs() < 0.35, "{t0:?}");
        assert!((t1[0] - 2.0).abs() < 0.3, "{t1:?}");
        assert!((t1[1] - 1.0).abs() < 0.35, "{t1:?}");
    }

    #[test]
    fn a_rare_label_follows_the_pool_and_slopes_never_invert() {
        let mut c = Calibrator::new(2, 500, 20.0, 5.0, 3, 0.05);
        let mut s = 5u64;
        for _ in 0..300 {
            let e = [4.0 * lcg(&mut s) - 2.0, -3.0];
            // Label 0 is under-confident by a factor 2; label 1 is never true (no signal).
            let y = [(lcg(&mut s) < sigmoid(2.0 * e[0])) as u8, 0];
            c.push(&e, &[0.0, -3.0], &y);
        }
        assert!(c.params(0)[0] > 1.6, "{:?}", c.params(0));
        assert!(c.params(1)[0] >= 0.05 && c.params(1)[1] >= 0.05);
        // Anti-correlated truth cannot flip the map.
        let mut c = Calibrator::new(1, 500, 1.0, 1.0, 5, 0.05);
        for i in 0..400 {
            let e = if i % 2 == 0 { 2.0 } else { -2.0 };
            c.push(&[e], &[0.0], &[(e < 0.0) as u8]);
        }
        assert_eq!(c.params(0)[0], 0.05);
    }

    #[test]
    fn the_window_slides() {
        let mut c = Calibrator::new(1, 3, 1.0, 1.0, 2, 0.05);
        for _ in 0..10 {
            c.push(&[1.0], &[0.0], &[1]);
        }
        assert_eq!(c.len(), 3);
    }
}
