//! The reputation updates: docs/PAPER-METHOD.md §5's multiplicative update (what `method = "paper"` runs), and the
//! parts the `adaptive` method composes (docs/METHOD.md §4): credits divided by a running credit
//! scale, a discounted mean credit per reporter, fixed-share mixing. Pure functions of their
//! inputs; [`CreditMemory`] is the little state the discounted update carries between rounds.

use crate::method::adaptive::pool::decay;

/// The paper method's `w_i <- w_i exp(eta phi_i) / sum_j w_j exp(eta phi_j)`. The exponent is shifted by its
/// maximum, which cancels in the ratio and keeps `exp` from overflowing on a huge credit.
pub fn multiplicative(w: &[f64], phi: &[f64], eta: f64) -> Vec<f64> {
    let m = phi
        .iter()
        .map(|p| eta * p)
        .fold(f64::NEG_INFINITY, f64::max);
    let raw: Vec<f64> = w
        .iter()
        .zip(phi)
        .map(|(wi, p)| wi * (eta * p - m).exp())
        .collect();
    let s: f64 = raw.iter().sum();
    raw.iter().map(|r| r / s).collect()
}

/// Fixed-share mixing `w <- (1 - alpha) w + alpha / n` (docs/METHOD.md §4): no reporter falls
/// below `alpha / n`. `alpha = 0` returns `w` untouched.
pub fn fixed_share(w: &[f64], alpha: f64) -> Vec<f64> {
    if alpha == 0.0 {
        return w.to_vec();
    }
    let n = w.len() as f64;
    w.iter().map(|&x| (1.0 - alpha) * x + alpha / n).collect()
}

/// The discounted update: a softmax of each reporter's recent mean credit `m_i = S_i / (D_i +
/// prior_rounds)`, its slope cut to a twentieth beyond `cap`: `w_i ~ exp(beta * (min(m_i, cap) +
/// max(0, m_i - cap) / 20))`. Below the cap this is `beta * m_i`; beyond it a very good reporter
/// gains slowly, so it does not crowd out the others that also help (they keep the weights the
/// hard cap this replaces gave them, which the benchmark suite's accuracy depends on), yet the
/// better of two always ranks higher (the hard `min(m_i, cap)` made a 97% reporter equal to a
/// 70% one once both passed the cap). A reporter that turns harmful (negative credit) falls as
/// fast as its credit. It depends on the credits remembered in `mem` only, not on the
/// reputations before.
/// The slope of [`discounted`]'s score beyond the cap, relative to below it.
pub const BEYOND_CAP: f64 = 0.05;

pub fn discounted(mem: &CreditMemory, prior_rounds: f64, beta: f64, cap: f64) -> Vec<f64> {
    let score: Vec<f64> = mem
        .sum
        .iter()
        .zip(&mem.count)
        .map(|(&s, &c)| {
            let den = c + prior_rounds;
            let m = if den > 0.0 { s / den } else { 0.0 };
            beta * (m.min(cap) + (m - cap).max(0.0) * BEYOND_CAP)
        })
        .collect();
    let top = score.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    let e: Vec<f64> = score.iter().map(|v| (v - top).exp()).collect();
    let z: f64 = e.iter().sum();
    e.iter().map(|v| v / z).collect()
}

/// Reporters outside `coalition` keep their weight `w[i]` (absence says nothing about accuracy);
/// the coalition shares the rest in the proportions `new` gives it. With everyone present (or
/// nobody) `new` is returned as it is; a degenerate share returns `w`.
pub fn keep_absent(w: &[f64], new: Vec<f64>, coalition: &[usize]) -> Vec<f64> {
    let n = w.len();
    if coalition.len() == n || coalition.is_empty() {
        return new;
    }
    let mut present = vec![false; n];
    for &i in coalition {
        present[i] = true;
    }
    let absent: f64 = (0..n).filter(|&i| !present[i]).map(|i| w[i]).sum();
    let share: f64 = coalition.iter().map(|&i| new[i]).sum();
    if share <= 0.0 || !share.is_finite() {
        return w.to_vec();
    }
    (0..n)
        .map(|i| {
            if present[i] {
                new[i] * (1.0 - absent) / share
            } else {
                w[i]
            }
        })
        .collect()
}

/// What the adaptive reputation update remembers of past credits.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct CreditMemory {
    /// Decayed sum of the per-round mean `|phi|` and its decayed count: the credit scale.
    scale_num: f64,
    scale_den: f64,
    /// Per reporter: discounted sum of scaled credits and discounted count of its rounds.
    sum: Vec<f64>,
    count: Vec<f64>,
}

impl CreditMemory {
    pub fn new(n: usize) -> Self {
        Self {
            scale_num: 0.0,
            scale_den: 0.0,
            sum: vec![0.0; n],
            count: vec![0.0; n],
        }
    }

    /// The typical `|phi|` (1 until a round has been credited).
    pub fn scale(&self) -> f64 {
        if self.scale_den > 0.0 {
            self.scale_num / self.scale_den
        } else {
            1.0
        }
    }

    /// The memory after a round with credits `phi` (all `n` reporters) over `coalition`: the
    /// credit scale takes in the round's mean `|phi|` (half-life `scale_half_life` rounds, 0:
    /// the scale stays 1), and each member's discounted sum takes in its credit divided by the
    /// scale (half-life `memory` of its rounds).
    pub fn after(
        &self,
        phi: &[f64],
        coalition: &[usize],
        scale_half_life: f64,
        memory: f64,
    ) -> Self {
        let mut st = self.clone();
        if scale_half_life > 0.0 {
            let g = decay(1.0, scale_half_life);
            let m = if coalition.is_empty() {
                0.0
            } else {
                coalition.iter().map(|&i| phi[i].abs()).sum::<f64>() / coalition.len() as f64
            };
            st.scale_num = g * st.scale_num + m;
            st.scale_den = g * st.scale_den + 1.0;
        }
        let s = st.scale();
        let g = decay(1.0, memory);
        for &i in coalition {
            let x = if s > 0.0 { phi[i] / s } else { 0.0 };
            st.sum[i] = g * st.sum[i] + x;
            st.count[i] = g * st.count[i] + 1.0;
        }
        st
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn absent_reporters_keep_their_weight() {
        let w = [0.5, 0.3, 0.2];
        let out = keep_absent(&w, vec![0.1, 0.6, 0.3], &[0, 1]);
        assert_eq!(out[2], 0.2);
        assert!((out.iter().sum::<f64>() - 1.0).abs() < 1e-15);
        assert!((out[1] / out[0] - 6.0).abs() < 1e-12);
        assert_eq!(
            keep_absent(&w, vec![0.1, 0.6, 0.3], &[0, 1, 2]),
            [0.1, 0.6, 0.3]
        );
    }

    #[test]
    fn discounted_follows_recent_credit_compressed_beyond_the_cap() {
        let mut m = CreditMemory::new(2);
        for _ in 0..50 {
            m = m.after(&[1.0, -1.0], &[0, 1], 0.0, 30.0);
        }
        let w = discounted(&m, 10.0, 8.0, 0.25);
        assert!(w[0] > w[1]);
        // The good reporter's score is 8 * (0.25 + (m - 0.25) / 10), the bad one's 8 * m: far
        // below the 16 m an uncompressed softmax gives.
        let gap = (w[0] / w[1]).ln();
        assert!(gap > 2.0 && gap < 2.0 + 8.0, "{gap}");
        assert_eq!(fixed_share(&w, 0.0), w);
        let mixed = fixed_share(&[1.0, 0.0], 0.1);
        assert!((mixed[0] - 0.95).abs() < 1e-15 && (mixed[1] - 0.05).abs() < 1e-15);
    }

    #[test]
    fn a_better_reporter_always_ranks_higher_however_good_both_are() {
        // Two reporters both far beyond the cap, one with twice the credit of the other (a hard
        // cap made them equal), and a third that helps little.
        let mut m = CreditMemory::new(3);
        for _ in 0..200 {
            m = m.after(&[2.0, 1.0, 0.05], &[0, 1, 2], 0.0, 30.0);
        }
        let w = discounted(&m, 10.0, 8.0, 0.25);
        assert!(w[0] > w[1] && w[1] > w[2], "{w:?}");
        assert!(w[0] / w[1] > 1.3, "the better one clearly ahead: {w:?}");
        // Both past the cap, the worse of the two keeps most of what the cap gave it.
        assert!(w[1] > 0.2, "{w:?}");
        // The one that helps least keeps, after the fixed share, a share it can win back from.
        assert!(fixed_share(&w, 0.03)[2] > 0.01, "{w:?}");
    }
}
