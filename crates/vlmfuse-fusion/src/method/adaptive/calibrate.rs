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
    rounds: Window,
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
    /// Adds another pass's sums to these.
    fn merge(&mut self, o: &Acc) {
        for i in 0..3 {
            self.g[i] += o.g[i];
            for j in 0..=i {
                self.h[i][j] += o.h[i][j];
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

/// Lanes of the sums of one pass: observation `i` adds to lane `i % LANES`, and the lanes are
/// added up in a fixed order at the end, so the sums are the same bits on every path.
const LANES: usize = 4;

/// `exp(x)` for `x <= 0` by arithmetic alone (Cody–Waite reduction by `ln 2`, the degree-13
/// Taylor polynomial of `e^r` on `|r| <= ln 2 / 2`, the power of two built from its bits):
/// within 2 ulp of the correctly rounded value, 0 below -708, and no call and no branch, so
/// that a pass's sigmoids vectorise. The same operations on every path give the same bits.
#[inline(always)]
fn exp_nonpositive(x: f64) -> f64 {
    const MAGIC: f64 = 6755399441055744.0; // 1.5 * 2^52: adding it rounds to an integer
    const LN2_HI: f64 = 6.931_471_803_691_238e-1; // ln 2, the high part: 0x3fe62e42fee00000
    const LN2_LO: f64 = 1.908_214_929_270_587_7e-10; // ln 2 - LN2_HI: 0x3dea39ef35793c76
    let xc = x.max(-708.0);
    let shifted = xc * std::f64::consts::LOG2_E + MAGIC;
    let n = shifted - MAGIC;
    let r = (xc - n * LN2_HI) - n * LN2_LO;
    let mut poly = 1.0 / 6_227_020_800.0; // 1/13!
    for c in [
        1.0 / 479_001_600.0,
        1.0 / 39_916_800.0,
        1.0 / 3_628_800.0,
        1.0 / 362_880.0,
        1.0 / 40_320.0,
        1.0 / 5_040.0,
        1.0 / 720.0,
        1.0 / 120.0,
        1.0 / 24.0,
        1.0 / 6.0,
        0.5,
        1.0,
        1.0,
    ] {
        poly = poly * r + c;
    }
    // The integer n sits in the low bits of `shifted`; 2^n is (n + 1023) in the exponent field.
    let scale = f64::from_bits(
        (shifted.to_bits().wrapping_sub(MAGIC.to_bits()))
            .wrapping_add(1023)
            .wrapping_shl(52),
    );
    let v = poly * scale;
    if x < -708.0 {
        0.0
    } else {
        v
    }
}

/// The logistic sigmoid of [`crate::signals::sigmoid`] on [`exp_nonpositive`]: what a refit
/// fits with (within a few ulp of it; the calibrated probabilities served use the former).
#[inline(always)]
fn sigmoid_fit(z: f64) -> f64 {
    let e = exp_nonpositive(-z.abs());
    let num = if z >= 0.0 { 1.0 } else { e };
    num / (1.0 + e)
}

/// One pass of a refit over observations `(x, y)` (`y = 2`: unknown, skipped) at parameters `th`: the gradient and the
/// lower triangle of the Hessian of the negative log-likelihood ([`solve3`] reads no other).
/// AVX2 where the processor has it: `LANES` observations a step, the same bits as elsewhere
/// (no FMA; the lanes are the sums' order everywhere).
fn pass(th: &Params, x: &[[f64; 2]], y: &[f64]) -> Acc {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: the feature this function is compiled for was just detected.
        return unsafe { pass_avx2(th, x, y) };
    }
    pass_body(th, x, y)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn pass_avx2(th: &Params, x: &[[f64; 2]], y: &[f64]) -> Acc {
    pass_body(th, x, y)
}

#[inline(always)]
fn pass_body(th: &Params, x: &[[f64; 2]], y: &[f64]) -> Acc {
    // Sums per lane: g = [r e, r q, r], h = [w e e, w q e, w q q, w e, w q, w].
    let mut g = [[0.0f64; LANES]; 3];
    let mut h = [[0.0f64; LANES]; 6];
    let n = x.len().min(y.len());
    let mut add = |j: usize, xi: [f64; 2], yi: f64| {
        let (e, q) = (xi[0], xi[1]);
        let p = sigmoid_fit(th[0] * e + th[1] * q + th[2]);
        // A label of unknown truth (`y = 2`, partial feedback) fits nothing: its terms are
        // zeros (adding `0` or `-0` leaves every sum as it was).
        let known = if yi <= 1.0 { 1.0 } else { 0.0 };
        let r = (p - yi) * known;
        let w = p * (1.0 - p) * known;
        let (we, wq) = (w * e, w * q);
        g[0][j] += r * e;
        g[1][j] += r * q;
        g[2][j] += r;
        h[0][j] += we * e;
        h[1][j] += wq * e;
        h[2][j] += wq * q;
        h[3][j] += we;
        h[4][j] += wq;
        h[5][j] += w;
    };
    let full = n - n % LANES;
    for (xs, ys) in x[..full]
        .chunks_exact(LANES)
        .zip(y[..full].chunks_exact(LANES))
    {
        for j in 0..LANES {
            add(j, xs[j], ys[j]);
        }
    }
    for i in full..n {
        add(i - full, x[i], y[i]);
    }
    let total = |v: &[f64; LANES]| (v[0] + v[1]) + (v[2] + v[3]);
    let (g, h) = (g.map(|v| total(&v)), h.map(|v| total(&v)));
    Acc {
        g,
        h: [[h[0], 0.0, 0.0], [h[1], h[2], 0.0], [h[3], h[4], h[5]]],
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
            rounds: Window::default(),
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
        self.rounds.push_back(&x, y);
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
        // Each label's observations are one contiguous run of the window (see `Window`); the
        // pooled fit adds the labels' sums in label order.
        for _ in 0..self.steps {
            let mut acc = Acc::default();
            for k in 0..self.l {
                let (x, y) = self.rounds.label(k);
                acc.merge(&pass(&self.pooled, x, y));
            }
            self.pooled = self.clamp(acc.step(self.pooled, IDENTITY, self.pooled_prior));
        }
        let centre = self.pooled;
        for k in 0..self.l {
            let (x, y) = self.rounds.label(k);
            let mut th = self.per_label[k];
            for _ in 0..self.steps {
                th = self.clamp(pass(&th, x, y).step(th, centre, self.label_prior));
            }
            self.per_label[k] = th;
        }
    }
}

/// The calibration's window of labelled rounds, kept per label as one contiguous run of
/// `(evidence, prior log-odds)` and truth (2: unknown) in round order, so that a refit reads
/// each label's observations straight from memory (gathering them from per-round rows cost as
/// much as the fit). Rows are appended at the end and retired from the front; the retired
/// prefix is dropped once it is as long as the live part (amortised O(1) per round). Saved as
/// the list of rounds it always was: `[(x per label, truth per label), ...]`, oldest first.
#[derive(Debug, Clone, Default)]
struct Window {
    /// Per label: the rows pushed since the last compaction.
    x: Vec<Vec<[f64; 2]>>,
    y: Vec<Vec<f64>>,
    /// Retired rows at the front of every run.
    start: usize,
}

impl Window {
    fn len(&self) -> usize {
        self.y.first().map_or(0, |y| y.len() - self.start)
    }

    fn push_back(&mut self, x: &[[f64; 2]], y: &[u8]) {
        if self.x.is_empty() {
            self.x = vec![Vec::new(); x.len()];
            self.y = vec![Vec::new(); x.len()];
        }
        for (k, (&xk, &yk)) in x.iter().zip(y).enumerate() {
            self.x[k].push(xk);
            self.y[k].push(yk as f64);
        }
    }

    fn pop_front(&mut self) {
        if self.len() == 0 {
            return;
        }
        self.start += 1;
        if self.start >= self.len() {
            for (x, y) in self.x.iter_mut().zip(&mut self.y) {
                x.drain(..self.start);
                y.drain(..self.start);
            }
            self.start = 0;
        }
    }

    /// Label `k`'s live run, oldest first.
    fn label(&self, k: usize) -> (&[[f64; 2]], &[f64]) {
        (&self.x[k][self.start..], &self.y[k][self.start..])
    }

    /// The rounds, oldest first, as rows: `(x per label, truth per label)`.
    fn rows(&self) -> impl Iterator<Item = (Vec<[f64; 2]>, Vec<u8>)> + '_ {
        (self.start..self.start + self.len()).map(move |i| {
            (
                self.x.iter().map(|x| x[i]).collect(),
                self.y.iter().map(|y| y[i] as u8).collect(),
            )
        })
    }
}

impl PartialEq for Window {
    /// The same rounds, wherever the compaction left them.
    fn eq(&self, other: &Self) -> bool {
        self.len() == other.len() && self.rows().eq(other.rows())
    }
}

impl serde::Serialize for Window {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.collect_seq(self.rows())
    }
}

impl<'de> serde::Deserialize<'de> for Window {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        let rows = Vec::<(Vec<[f64; 2]>, Vec<u8>)>::deserialize(d)?;
        let mut w = Window::default();
        for (x, y) in &rows {
            if x.len() != y.len() || rows.first().is_some_and(|(x0, _)| x0.len() != x.len()) {
                return Err(serde::de::Error::custom(
                    "calibration window: rows of different lengths",
                ));
            }
            w.push_back(x, y);
        }
        Ok(w)
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

    /// The refit as first written: one pass per Newton step, the sigmoid computed inside the
    /// accumulation, the whole Hessian summed.
    fn reference_refit(c: &mut Calibrator) {
        let add = |acc: &mut Acc, th: &Params, x: [f64; 2], y: u8| {
            let f = [x[0], x[1], 1.0];
            let p = sigmoid(th[0] * f[0] + th[1] * f[1] + th[2]);
            let r = p - y as f64;
            let w = p * (1.0 - p);
            for i in 0..3 {
                acc.g[i] += r * f[i];
                for j in 0..3 {
                    acc.h[i][j] += w * f[i] * f[j];
                }
            }
        };
        for _ in 0..c.steps {
            let mut acc = Acc::default();
            for (x, y) in c.rounds.rows() {
                for k in (0..c.l).filter(|&k| y[k] <= 1) {
                    add(&mut acc, &c.pooled, x[k], y[k]);
                }
            }
            c.pooled = c.clamp(acc.step(c.pooled, IDENTITY, c.pooled_prior));
        }
        let centre = c.pooled;
        for k in 0..c.l {
            let mut th = c.per_label[k];
            for _ in 0..c.steps {
                let mut acc = Acc::default();
                for (x, y) in c.rounds.rows().filter(|(_, y)| y[k] <= 1) {
                    add(&mut acc, &th, x[k], y[k]);
                }
                th = c.clamp(acc.step(th, centre, c.label_prior));
            }
            c.per_label[k] = th;
        }
    }

    #[test]
    fn the_vectorised_refit_gives_the_reference_fit() {
        // Partial truths (2 = unknown) included, and two Newton steps per refit.
        let mut fast = Calibrator::new(3, 60, 20.0, 5.0, 2, 0.05);
        let mut slow = fast.clone();
        let mut s = 3u64;
        for round in 0..200 {
            let e: Vec<f64> = (0..3).map(|_| 8.0 * lcg(&mut s) - 4.0).collect();
            let p: Vec<f64> = (0..3).map(|_| 3.0 * lcg(&mut s) - 2.0).collect();
            let y: Vec<u8> = (0..3)
                .map(|k| {
                    if round % 7 == k {
                        2
                    } else {
                        (lcg(&mut s) < sigmoid(0.7 * e[k] + p[k])) as u8
                    }
                })
                .collect();
            fast.push(&e, &p, &y);
            // The same window, refitted from the same start the first way.
            slow = Calibrator {
                rounds: fast.rounds.clone(),
                pushed: fast.pushed,
                ..slow
            };
            reference_refit(&mut slow);
            let close = |a: &Params, b: &Params| {
                a.iter()
                    .zip(b)
                    .all(|(x, y)| (x - y).abs() <= 1e-12 * (1.0 + y.abs()))
            };
            assert!(close(&fast.pooled, &slow.pooled), "round {round}");
            for k in 0..3 {
                assert!(
                    close(&fast.per_label[k], &slow.per_label[k]),
                    "round {round}"
                );
            }
            // Each refit starts from the other's last fit: the two are compared step by step.
            slow.pooled = fast.pooled;
            slow.per_label = fast.per_label.clone();
        }
    }

    #[test]
    fn exp_by_arithmetic_is_within_two_ulp_of_libm() {
        let ulps = |a: f64, b: f64| (a.to_bits() as i64 - b.to_bits() as i64).unsigned_abs();
        let mut x = 0.0f64;
        let mut worst = 0;
        while x >= -708.0 {
            for v in [x, x - 1e-7, x * 0.999_999_7] {
                if v >= -708.0 {
                    worst = worst.max(ulps(exp_nonpositive(v), v.exp()));
                }
            }
            x -= 0.0137;
        }
        assert!(worst <= 2, "{worst} ulp");
        assert_eq!(exp_nonpositive(0.0), 1.0);
        assert_eq!(exp_nonpositive(-0.0), 1.0);
        assert_eq!(exp_nonpositive(-709.0), 0.0);
        assert_eq!(exp_nonpositive(f64::NEG_INFINITY), 0.0);
        for z in [-40.0, -3.0, -0.5, 0.0, 0.5, 3.0, 40.0, 800.0, -800.0] {
            assert!((sigmoid_fit(z) - sigmoid(z)).abs() <= 4.0 * f64::EPSILON * sigmoid(z));
        }
    }

    #[test]
    fn a_pass_gives_the_same_bits_on_every_path() {
        let mut s = 9u64;
        for n in [0usize, 1, 3, 4, 5, 63, 500] {
            let x: Vec<[f64; 2]> = (0..n)
                .map(|_| [60.0 * lcg(&mut s) - 30.0, 6.0 * lcg(&mut s) - 3.0])
                .collect();
            let y: Vec<f64> = (0..n).map(|_| (lcg(&mut s) < 0.3) as u8 as f64).collect();
            let th = [0.8, 1.3, -0.2];
            let (a, b) = (pass(&th, &x, &y), pass_body(&th, &x, &y));
            assert_eq!(a.g.map(f64::to_bits), b.g.map(f64::to_bits), "n {n}");
            assert_eq!(a.h, b.h, "n {n}");
        }
    }

    #[test]
    fn the_window_is_saved_as_the_list_of_rounds_it_was() {
        use std::collections::VecDeque;
        let mut c = Calibrator::new(2, 3, 1.0, 1.0, 1, 0.05);
        let mut rows: VecDeque<(Vec<[f64; 2]>, Vec<u8>)> = VecDeque::new();
        for i in 0..11u8 {
            let (e, p, y) = ([i as f64, -(i as f64)], [0.5, -0.25 * i as f64], [i % 2, 2]);
            c.push(&e, &p, &y);
            rows.push_back((vec![[e[0], p[0]], [e[1], p[1]]], y.to_vec()));
            if rows.len() > 3 {
                rows.pop_front();
            }
            let saved = serde_json::to_value(&c.rounds).unwrap();
            assert_eq!(saved, serde_json::to_value(&rows).unwrap(), "after {i}");
            let back: Window = serde_json::from_value(saved).unwrap();
            assert_eq!(back, c.rounds);
        }
        // A restored calibrator refits as the one that was saved.
        let mut back: Calibrator =
            serde_json::from_str(&serde_json::to_string(&c).unwrap()).unwrap();
        c.push(&[1.0, 2.0], &[0.0, 0.0], &[1, 0]);
        back.push(&[1.0, 2.0], &[0.0, 0.0], &[1, 0]);
        assert_eq!(back, c);
        assert!(serde_json::from_str::<Window>("[[[[1.0, 2.0]], [1, 0]]]").is_err());
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
