//! Signal conditioning for the rules: smoothing, differentiation, "held for" levels, and the
//! segmentation that keeps every window inside a stretch of valid, closely spaced samples.
//!
//! Every function is O(samples): local windows are capped at [`MAX_WINDOW_SAMPLES`] on each
//! side (a 1 s window at 100 Hz fits; at a higher rate the window shrinks instead of the work
//! growing), and the "held for" levels use monotonic queues.

use std::collections::VecDeque;

/// At most this many samples on each side of a local window.
pub(crate) const MAX_WINDOW_SAMPLES: usize = 100;

/// Two timestamps this close are the same instant for duration tests: 10 Hz timestamps written
/// as decimals do not subtract to exact tenths.
const EPS_S: f64 = 1e-6;

/// Share of non-missing samples.
pub(crate) fn coverage(v: &[Option<f64>]) -> f64 {
    if v.is_empty() {
        return 0.0;
    }
    v.iter().filter(|x| x.is_some()).count() as f64 / v.len() as f64
}

/// `[lo, hi]` (inclusive) of the samples within `half_s` of each sample, capped.
fn windows(t: &[f64], half_s: f64) -> Vec<(usize, usize)> {
    let n = t.len();
    let mut out = Vec::with_capacity(n);
    let (mut lo, mut hi) = (0usize, 0usize);
    for i in 0..n {
        while t[i] - t[lo] > half_s + EPS_S {
            lo += 1;
        }
        if hi < i {
            hi = i;
        }
        while hi + 1 < n && t[hi + 1] - t[i] <= half_s + EPS_S {
            hi += 1;
        }
        out.push((
            lo.max(i.saturating_sub(MAX_WINDOW_SAMPLES)),
            hi.min(i + MAX_WINDOW_SAMPLES),
        ));
    }
    out
}

/// Centred moving average of the valid values within `width_s`. A missing sample gets its
/// neighbours' average, so an isolated dropped cell does not break a run; a stretch of missing
/// samples longer than the window stays missing.
pub(crate) fn moving_average(t: &[f64], v: &[Option<f64>], width_s: f64) -> Vec<Option<f64>> {
    windows(t, width_s / 2.0)
        .into_iter()
        .map(|(lo, hi)| {
            let (mut sum, mut k) = (0.0, 0usize);
            for x in v[lo..=hi].iter().flatten() {
                sum += x;
                k += 1;
            }
            (k > 0).then(|| sum / k as f64)
        })
        .collect()
}

/// Local least-squares slope (units per second) over `width_s`, centred. Needs 3 valid samples
/// spread over at least a quarter of the width, so an edge or a gap gives `None`, not a slope
/// from two noisy points.
pub(crate) fn slope(t: &[f64], v: &[Option<f64>], width_s: f64) -> Vec<Option<f64>> {
    windows(t, width_s / 2.0)
        .into_iter()
        .enumerate()
        .map(|(i, (lo, hi))| {
            // Times relative to the centre sample: no cancellation however large t is.
            let pts = (lo..=hi).filter_map(|k| v[k].map(|y| (t[k] - t[i], y)));
            let (mut n, mut su, mut sy) = (0.0, 0.0, 0.0);
            let (mut umin, mut umax) = (f64::INFINITY, f64::NEG_INFINITY);
            for (u, y) in pts.clone() {
                n += 1.0;
                su += u;
                sy += y;
                umin = umin.min(u);
                umax = umax.max(u);
            }
            if n < 3.0 || umax - umin < width_s / 4.0 {
                return None;
            }
            let (mu, my) = (su / n, sy / n);
            let (mut suu, mut suy) = (0.0, 0.0);
            for (u, y) in pts {
                suu += (u - mu) * (u - mu);
                suy += (u - mu) * (y - my);
            }
            (suu > 0.0).then(|| suy / suu)
        })
        .collect()
}

/// Maximal stretches `[start, end)` of samples where `ok(i)` holds and consecutive samples are
/// at most `max_gap_s` apart.
pub(crate) fn segments(
    t: &[f64],
    ok: impl Fn(usize) -> bool,
    max_gap_s: f64,
) -> Vec<(usize, usize)> {
    let mut out = Vec::new();
    let mut start: Option<usize> = None;
    for i in 0..t.len() {
        let joins = i > 0 && t[i] - t[i - 1] <= max_gap_s + EPS_S;
        match (start, ok(i)) {
            (Some(s), true) if !joins => {
                out.push((s, i));
                start = Some(i);
            }
            (Some(_), true) => {}
            (Some(s), false) => {
                out.push((s, i));
                start = None;
            }
            (None, true) => start = Some(i),
            (None, false) => {}
        }
    }
    if let Some(s) = start {
        out.push((s, t.len()));
    }
    out
}

/// A level held over a stretch of samples.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct Held {
    /// The level: every sample of the stretch is at or below it ([`held_low`]) or at or above
    /// it ([`held_high`]).
    pub level: f64,
    pub start: usize,
    pub end: usize,
}

/// The lowest level `v` stays at or below for at least `min_s`: the minimum, over stretches of
/// `min_s`, of the stretch's maximum. "Decelerating at 2 m/s² for 0.5 s" is exactly
/// `held_low(accel, 0.5).level <= -2`, and one noise spike cannot lower it. `None` when no
/// stretch of valid samples lasts `min_s`.
pub(crate) fn held_low(t: &[f64], v: &[Option<f64>], min_s: f64, max_gap_s: f64) -> Option<Held> {
    let mut best: Option<Held> = None;
    for (s, e) in segments(t, |i| v[i].is_some(), max_gap_s) {
        let val = |k: usize| v[k].unwrap_or(f64::NAN);
        let mut q: VecDeque<usize> = VecDeque::new();
        let mut j = s; // next sample to push
        for i in s..e {
            while q.front().is_some_and(|&f| f < i) {
                q.pop_front();
            }
            // Grow the window [i, j-1] until it lasts min_s.
            while j < e && (j <= i || t[j - 1] - t[i] < min_s - EPS_S) {
                while q.back().is_some_and(|&b| val(b) <= val(j)) {
                    q.pop_back();
                }
                q.push_back(j);
                j += 1;
            }
            if t[j - 1] - t[i] < min_s - EPS_S {
                break;
            }
            if let Some(&f) = q.front() {
                let level = val(f);
                if best.is_none_or(|b| level < b.level) {
                    best = Some(Held {
                        level,
                        start: i,
                        end: j - 1,
                    });
                }
            }
        }
    }
    best
}

/// The highest level `v` stays at or above for at least `min_s` ([`held_low`] mirrored).
pub(crate) fn held_high(t: &[f64], v: &[Option<f64>], min_s: f64, max_gap_s: f64) -> Option<Held> {
    let neg: Vec<Option<f64>> = v.iter().map(|x| x.map(|y| -y)).collect();
    held_low(t, &neg, min_s, max_gap_s).map(|h| Held {
        level: -h.level,
        ..h
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn t10(n: usize) -> Vec<f64> {
        (0..n).map(|i| i as f64 * 0.1).collect()
    }

    #[test]
    fn held_low_ignores_a_spike_and_finds_a_held_level() {
        let t = t10(50);
        let mut v: Vec<Option<f64>> = vec![Some(0.0); 50];
        v[5] = Some(-9.0); // one sample: not held
        for x in &mut v[20..26] {
            *x = Some(-2.0); // 0.5 s (6 samples at 10 Hz)
        }
        let h = held_low(&t, &v, 0.5, 1.0).unwrap();
        assert_eq!(h.level, -2.0);
        assert_eq!((h.start, h.end), (20, 25));
        let h = held_low(&t, &v, 0.6, 1.0).unwrap();
        assert_eq!(h.level, 0.0);
    }

    #[test]
    fn a_gap_breaks_a_run() {
        let mut t = t10(20);
        for x in &mut t[10..] {
            *x += 5.0;
        }
        let v = vec![Some(-3.0); 20];
        assert!(held_low(&t, &v, 1.0, 1.0).is_none());
        assert_eq!(held_low(&t, &v, 0.9, 1.0).unwrap().level, -3.0);
    }

    #[test]
    fn slope_of_a_line() {
        let t = t10(30);
        let v: Vec<Option<f64>> = t.iter().map(|x| Some(3.0 - 2.0 * x)).collect();
        let s = slope(&t, &v, 1.0);
        for x in s.iter().flatten() {
            assert!((x + 2.0).abs() < 1e-9);
        }
        assert!(s[15].is_some());
    }
}
