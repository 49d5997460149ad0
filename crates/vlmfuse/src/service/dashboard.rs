//! What the operator page (`/ui`, docs/UI.md) shows, kept up to date as events commit: the
//! writer calls [`Dashboard::on_round`] and [`Dashboard::on_feedback`] after each commit, and a
//! start seeds it from the latest events in the store. Every aggregate lives in a window bounded
//! by `[ui]`, so memory is fixed and a page load costs the same at a hundred rounds as at a
//! million; nothing here scans the store or the engine per request.

use crate::config::UiSection;
use serde::Serialize;
use std::collections::VecDeque;
use vlmfuse_fusion::metrics::ECE_BINS;
use vlmfuse_fusion::{Inference, Round};

/// Latencies kept per reporter for the percentiles.
const LATENCY_WINDOW: usize = 1000;
/// Alarm starts kept per reporter.
const ALARMS_KEPT: usize = 100;

/// One point of the reputation chart: the reputations after a labelled round.
#[derive(Debug, Clone, Serialize)]
pub struct HistPoint {
    /// Feedback events applied so far (1 for the first).
    pub labelled: u64,
    pub round_id: String,
    pub w: Vec<f64>,
}

/// A labelled event as the windows keep it.
#[derive(Debug, Clone)]
struct Labelled {
    /// `n * L`: the reporter's report (0/1), or 2 where it was absent.
    reports: Vec<u8>,
    /// `L`: 0/1 learned from the event, 2 unknown.
    truth: Vec<u8>,
}

/// A fused round as the windows keep it.
#[derive(Debug, Clone)]
struct Recent {
    coalition: Vec<usize>,
    theta_pos: Vec<f64>,
    theta_neg: Vec<f64>,
    /// `n * L` reports (2: absent) and the fused prediction, for the agreement.
    reports: Vec<u8>,
    pred: Vec<u8>,
    decision: Option<String>,
}

#[derive(Debug, Clone, Default)]
struct ReporterHealth {
    latencies: VecDeque<f64>,
    failures: u64,
}

/// The page's aggregates.
#[derive(Debug, Clone)]
pub struct Dashboard {
    cfg: UiSection,
    n: usize,
    l: usize,
    /// Every `stride`-th labelled event, thinned by halves when it outgrows `history_points`.
    stride: u64,
    points: Vec<HistPoint>,
    latest: Option<HistPoint>,
    /// Per reporter: its latest `2 * drift_window` credit shares (rounds it was in), newest last.
    credits: Vec<VecDeque<f64>>,
    alarm: Vec<bool>,
    alarm_at: Vec<VecDeque<u64>>,
    labelled: VecDeque<Labelled>,
    /// `n * L` counts over `labelled`: true positives, positives, false positives, negatives.
    tp: Vec<u64>,
    pos: Vec<u64>,
    fp: Vec<u64>,
    neg: Vec<u64>,
    recent: VecDeque<Recent>,
    /// Posteriors at inference and the truth learned, for the reliability diagram.
    calibration: VecDeque<(Vec<f64>, Vec<u8>)>,
    health: Vec<ReporterHealth>,
}

/// Panel data, serialised into `/ui/api/summary`.
#[derive(Debug, Serialize)]
pub struct Panels {
    pub reputation_history: History,
    pub drift: Drift,
    pub reliability: Reliability,
    pub calibration: Calibration,
    pub serving: Serving,
    pub reporters_health: Vec<ReporterHealthOut>,
}

#[derive(Debug, Serialize)]
pub struct History {
    pub points: Vec<HistPoint>,
}

#[derive(Debug, Serialize)]
pub struct Drift {
    pub window: usize,
    pub threshold: f64,
    pub reporters: Vec<DriftOut>,
}

#[derive(Debug, Serialize)]
pub struct DriftOut {
    pub reporter: String,
    /// Mean credit share (its Shapley credit over the round's total |credit|) over the latest
    /// window (null until the reporter was in a round).
    pub recent: Option<f64>,
    /// Mean credit share over the window before (null until both windows are full).
    pub previous: Option<f64>,
    pub drop: Option<f64>,
    pub alarm: bool,
    pub alarm_at: Vec<AlarmAt>,
}

#[derive(Debug, Serialize)]
pub struct AlarmAt {
    pub labelled: u64,
}

#[derive(Debug, Serialize)]
pub struct Reliability {
    pub overall: RateMaps,
    /// Null before the first round.
    pub recent: Option<RateMaps>,
}

/// `[reporter][label]` rates; null where nothing was seen.
#[derive(Debug, Serialize)]
pub struct RateMaps {
    pub rounds: usize,
    pub tpr: Vec<Vec<Option<f64>>>,
    pub fpr: Vec<Vec<Option<f64>>>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub positives: Option<Vec<Vec<u64>>>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub negatives: Option<Vec<Vec<u64>>>,
}

#[derive(Debug, Serialize)]
pub struct Calibration {
    pub window: usize,
    pub rounds: usize,
    /// (posterior, known truth) pairs counted.
    pub pairs: u64,
    /// Null without pairs.
    pub ece: Option<f64>,
    pub bins: Vec<CalBin>,
}

#[derive(Debug, Serialize)]
pub struct CalBin {
    pub lo: f64,
    pub hi: f64,
    pub count: u64,
    pub mean_q: Option<f64>,
    pub freq: Option<f64>,
}

#[derive(Debug, Serialize)]
pub struct Serving {
    pub window: usize,
    /// Decisions of the latest rounds, by predictor (rounds stored before decisions were kept
    /// count as `unknown`).
    pub decisions: std::collections::BTreeMap<String, u64>,
    /// Per reporter: the share of its labels (rounds it was in) equal to the fused ones.
    pub agreement: Vec<Option<f64>>,
}

#[derive(Debug, Serialize)]
pub struct ReporterHealthOut {
    pub latency_ms: Percentiles,
    pub failures: u64,
}

#[derive(Debug, Serialize)]
pub struct Percentiles {
    pub count: usize,
    pub p50: Option<f64>,
    pub p95: Option<f64>,
    pub p99: Option<f64>,
}

/// Nearest-rank percentile of sorted values.
fn percentile(sorted: &[f64], p: f64) -> Option<f64> {
    if sorted.is_empty() {
        return None;
    }
    let rank = ((p * sorted.len() as f64).ceil() as usize).clamp(1, sorted.len());
    Some(sorted[rank - 1])
}

/// The smallest power of two that keeps `total` events within `cap` points.
fn stride_for(total: u64, cap: usize) -> u64 {
    let mut s = 1u64;
    while total.div_ceil(s) > cap as u64 {
        s *= 2;
    }
    s
}

fn ratio(num: u64, den: u64) -> Option<f64> {
    (den > 0).then(|| num as f64 / den as f64)
}

fn mean(xs: impl Iterator<Item = f64>) -> Option<f64> {
    let (s, c) = xs.fold((0.0, 0usize), |(s, c), x| (s + x, c + 1));
    (c > 0).then(|| s / c as f64)
}

/// `n * L` reports of a round: the reporter's 0/1, 2 for an absent reporter.
fn full_reports(round: &Round, n: usize, l: usize) -> Vec<u8> {
    let mut out = vec![2u8; n * l];
    for i in 0..n.min(round.present.len()) {
        if round.present[i] {
            if let Some(src) = round.reports.get(i * l..(i + 1) * l) {
                out[i * l..(i + 1) * l].copy_from_slice(src);
            }
        }
    }
    out
}

impl Dashboard {
    pub fn new(cfg: UiSection, n: usize, l: usize) -> Self {
        Self {
            cfg,
            n,
            l,
            stride: 1,
            points: Vec::new(),
            latest: None,
            credits: vec![VecDeque::new(); n],
            alarm: vec![false; n],
            alarm_at: vec![VecDeque::new(); n],
            labelled: VecDeque::new(),
            tp: vec![0; n * l],
            pos: vec![0; n * l],
            fp: vec![0; n * l],
            neg: vec![0; n * l],
            recent: VecDeque::new(),
            calibration: VecDeque::new(),
            health: vec![ReporterHealth::default(); n],
        }
    }

    /// A round committed (`decision`: the predictor that served it, if known).
    pub fn on_round(&mut self, round: &Round, inf: &Inference, decision: Option<&str>) {
        let s = &inf.signals;
        self.recent.push_back(Recent {
            coalition: s.coalition.clone(),
            theta_pos: s.theta_pos.clone(),
            theta_neg: s.theta_neg.clone(),
            reports: full_reports(round, self.n, self.l),
            pred: inf.pred.clone(),
            decision: decision.map(str::to_string),
        });
        while self.recent.len() > self.cfg.recent_rounds {
            self.recent.pop_front();
        }
    }

    /// A feedback event committed and applied: `labelled` events so far (this one included),
    /// the round's reports, the truth this event taught (2: not in it), the posteriors the round
    /// was served with, the credit per reporter (`present` says who was in the round) and the
    /// reputations after it.
    #[allow(clippy::too_many_arguments)]
    pub fn on_feedback(
        &mut self,
        labelled: u64,
        round_id: &str,
        round: &Round,
        truth: &[u8],
        q: &[f64],
        phi: &[f64],
        w_after: &[f64],
    ) {
        let point = HistPoint {
            labelled,
            round_id: round_id.to_string(),
            w: w_after.to_vec(),
        };
        if labelled.saturating_sub(1).is_multiple_of(self.stride) {
            self.points.push(point.clone());
            if self.points.len() > self.cfg.history_points {
                // Keep every other point: the chart stays evenly spaced over the whole history.
                let kept: Vec<HistPoint> = self.points.iter().step_by(2).cloned().collect();
                self.points = kept;
                self.stride *= 2;
            }
        }
        self.latest = Some(point);

        let w = self.cfg.drift_window;
        // Credit as a share of the round's total (|phi| summed over its members), so that the
        // alarm's threshold means the same whatever the value function's scale and the number
        // of labels: a reporter that carried a third of the credit and now carries none fell 0.33.
        let total: f64 = (0..self.n)
            .filter(|&i| round.present.get(i).copied().unwrap_or(false))
            .map(|i| phi.get(i).copied().unwrap_or(0.0).abs())
            .sum();
        for i in 0..self.n {
            if !round.present.get(i).copied().unwrap_or(false) {
                continue;
            }
            let share = if total > 0.0 {
                phi.get(i).copied().unwrap_or(0.0) / total
            } else {
                0.0
            };
            let c = &mut self.credits[i];
            c.push_back(share);
            while c.len() > 2 * w {
                c.pop_front();
            }
            let alarm = self
                .drift_of(i)
                .2
                .is_some_and(|d| d > self.cfg.drift_threshold);
            if alarm && !self.alarm[i] {
                let at = &mut self.alarm_at[i];
                at.push_back(labelled);
                while at.len() > ALARMS_KEPT {
                    at.pop_front();
                }
            }
            self.alarm[i] = alarm;
        }

        let ev = Labelled {
            reports: full_reports(round, self.n, self.l),
            truth: truth.to_vec(),
        };
        self.count(&ev, true);
        self.labelled.push_back(ev);
        while self.labelled.len() > self.cfg.reliability_window {
            let old = self.labelled.pop_front().expect("non-empty");
            self.count(&old, false);
        }
        self.calibration.push_back((q.to_vec(), truth.to_vec()));
        while self.calibration.len() > self.cfg.calibration_window {
            self.calibration.pop_front();
        }
    }

    /// One reporter answered (`Ok(latency in ms)`) or failed.
    pub fn on_reporter(&mut self, i: usize, result: Result<f64, ()>) {
        let Some(h) = self.health.get_mut(i) else {
            return;
        };
        match result {
            Ok(ms) => {
                h.latencies.push_back(ms);
                while h.latencies.len() > LATENCY_WINDOW {
                    h.latencies.pop_front();
                }
            }
            Err(()) => h.failures += 1,
        }
    }

    fn count(&mut self, ev: &Labelled, add: bool) {
        let step = |c: &mut u64| {
            if add {
                *c += 1
            } else {
                *c -= 1
            }
        };
        for i in 0..self.n {
            for k in 0..self.l {
                let r = ev.reports[i * self.l + k];
                let y = ev.truth[k];
                if r > 1 || y > 1 {
                    continue;
                }
                let at = i * self.l + k;
                if y == 1 {
                    step(&mut self.pos[at]);
                    if r == 1 {
                        step(&mut self.tp[at]);
                    }
                } else {
                    step(&mut self.neg[at]);
                    if r == 1 {
                        step(&mut self.fp[at]);
                    }
                }
            }
        }
    }

    /// (recent, previous, drop) mean credits of reporter `i`.
    fn drift_of(&self, i: usize) -> (Option<f64>, Option<f64>, Option<f64>) {
        let w = self.cfg.drift_window;
        let c = &self.credits[i];
        let split = c.len().saturating_sub(w);
        let recent = mean(c.iter().skip(split).copied());
        let previous = (c.len() == 2 * w)
            .then(|| mean(c.iter().take(w).copied()))
            .flatten();
        let drop = match (recent, previous) {
            (Some(r), Some(p)) => Some(p - r),
            _ => None,
        };
        (recent, previous, drop)
    }

    /// Seeds the aggregates from the store after a start: the latest events of each window, and
    /// the reputation chart thinned over the whole history (`labelled` events in all). Bounded:
    /// one pass over the feedback key for the chart, the windows' own sizes for the rest.
    pub fn seed(
        &mut self,
        store: &vlmfuse_store::Store,
        labelled: u64,
    ) -> Result<(), vlmfuse_store::StoreError> {
        let window = self
            .cfg
            .reliability_window
            .max(self.cfg.calibration_window)
            .max(2 * self.cfg.drift_window);
        for row in store.recent_labelled(window)? {
            let f = &row.feedback;
            self.on_feedback(
                f.labelled_order + 1,
                &row.round_id,
                &row.round,
                &f.truth,
                &row.q,
                &f.outcome.phi,
                &f.outcome.w_after,
            );
        }
        let mut recent = store.recent_rounds(None, self.cfg.recent_rounds)?;
        recent.reverse();
        for r in &recent {
            let decision = r.request.get("decision").and_then(|v| v.as_str());
            self.on_round(&r.round, &r.inference, decision);
        }
        let stride = stride_for(labelled, self.cfg.history_points);
        let mut points: Vec<HistPoint> = store
            .reputation_points(stride)?
            .into_iter()
            .map(|(labelled, round_id, w)| HistPoint {
                labelled,
                round_id,
                w,
            })
            .collect();
        self.latest = points.last().cloned();
        if points
            .last()
            .is_some_and(|p| !(p.labelled - 1).is_multiple_of(stride))
        {
            points.pop();
        }
        self.points = points;
        self.stride = stride;
        Ok(())
    }

    /// The reputation chart's points, oldest first, ending at the latest event.
    pub fn history(&self) -> Vec<HistPoint> {
        let mut pts = self.points.clone();
        if let Some(last) = &self.latest {
            if pts.last().is_none_or(|p| p.labelled != last.labelled) {
                pts.push(last.clone());
            }
        }
        pts
    }

    /// Every panel's numbers.
    pub fn panels(&self, reporters: &[String]) -> Panels {
        let (n, l) = (self.n, self.l);
        let grid = |f: &dyn Fn(usize) -> Option<f64>| -> Vec<Vec<Option<f64>>> {
            (0..n)
                .map(|i| (0..l).map(|k| f(i * l + k)).collect())
                .collect()
        };
        let counts = |v: &[u64]| -> Vec<Vec<u64>> {
            (0..n).map(|i| v[i * l..(i + 1) * l].to_vec()).collect()
        };
        let overall = RateMaps {
            rounds: self.labelled.len(),
            tpr: grid(&|a| ratio(self.tp[a], self.pos[a])),
            fpr: grid(&|a| ratio(self.fp[a], self.neg[a])),
            positives: Some(counts(&self.pos)),
            negatives: Some(counts(&self.neg)),
        };
        let recent = (!self.recent.is_empty()).then(|| {
            // Mean of the engine's contextual estimates over the rounds each reporter was in.
            let mut sp = vec![0.0; n * l];
            let mut sn = vec![0.0; n * l];
            let mut c = vec![0u64; n * l];
            for r in &self.recent {
                for (m, &i) in r.coalition.iter().enumerate() {
                    if i >= n {
                        continue;
                    }
                    for k in 0..l {
                        sp[i * l + k] += r.theta_pos.get(m * l + k).copied().unwrap_or(0.0);
                        sn[i * l + k] += r.theta_neg.get(m * l + k).copied().unwrap_or(0.0);
                        c[i * l + k] += 1;
                    }
                }
            }
            RateMaps {
                rounds: self.recent.len(),
                tpr: grid(&|a| (c[a] > 0).then(|| sp[a] / c[a] as f64)),
                fpr: grid(&|a| (c[a] > 0).then(|| sn[a] / c[a] as f64)),
                positives: None,
                negatives: None,
            }
        });

        let mut bins = [(0u64, 0.0f64, 0.0f64); ECE_BINS];
        for (q, t) in &self.calibration {
            for (k, &y) in t.iter().enumerate() {
                let Some(&p) = q.get(k) else { continue };
                if y > 1 || !p.is_finite() {
                    continue;
                }
                let b = ((p * ECE_BINS as f64).floor().max(0.0) as usize).min(ECE_BINS - 1);
                bins[b].0 += 1;
                bins[b].1 += p;
                bins[b].2 += y as f64;
            }
        }
        let pairs: u64 = bins.iter().map(|b| b.0).sum();
        let ece = (pairs > 0).then(|| {
            bins.iter()
                .filter(|b| b.0 > 0)
                .map(|&(c, ps, ys)| c as f64 / pairs as f64 * (ys / c as f64 - ps / c as f64).abs())
                .sum()
        });
        let calibration = Calibration {
            window: self.cfg.calibration_window,
            rounds: self.calibration.len(),
            pairs,
            ece,
            bins: bins
                .iter()
                .enumerate()
                .map(|(b, &(c, ps, ys))| CalBin {
                    lo: b as f64 / ECE_BINS as f64,
                    hi: (b + 1) as f64 / ECE_BINS as f64,
                    count: c,
                    mean_q: (c > 0).then(|| ps / c as f64),
                    freq: (c > 0).then(|| ys / c as f64),
                })
                .collect(),
        };

        let mut decisions = std::collections::BTreeMap::new();
        for r in &self.recent {
            *decisions
                .entry(r.decision.clone().unwrap_or_else(|| "unknown".into()))
                .or_insert(0) += 1;
        }
        let serving = Serving {
            window: self.cfg.recent_rounds,
            decisions,
            agreement: self.agreement(),
        };

        let drift = Drift {
            window: self.cfg.drift_window,
            threshold: self.cfg.drift_threshold,
            reporters: (0..n)
                .map(|i| {
                    let (recent, previous, drop) = self.drift_of(i);
                    DriftOut {
                        reporter: reporters.get(i).cloned().unwrap_or_default(),
                        recent,
                        previous,
                        drop,
                        alarm: self.alarm[i],
                        alarm_at: self.alarm_at[i]
                            .iter()
                            .map(|&labelled| AlarmAt { labelled })
                            .collect(),
                    }
                })
                .collect(),
        };
        let reporters_health = self
            .health
            .iter()
            .map(|h| {
                let mut s: Vec<f64> = h.latencies.iter().copied().collect();
                s.sort_by(f64::total_cmp);
                ReporterHealthOut {
                    latency_ms: Percentiles {
                        count: s.len(),
                        p50: percentile(&s, 0.50),
                        p95: percentile(&s, 0.95),
                        p99: percentile(&s, 0.99),
                    },
                    failures: h.failures,
                }
            })
            .collect();
        Panels {
            reputation_history: History {
                points: self.history(),
            },
            drift,
            reliability: Reliability { overall, recent },
            calibration,
            serving,
            reporters_health,
        }
    }

    /// The agreement of each reporter with the fused labels over the recent window (for the
    /// `vlmfuse_reporter_agreement` gauge).
    pub fn agreement(&self) -> Vec<Option<f64>> {
        let (n, l) = (self.n, self.l);
        let mut agree = vec![(0u64, 0u64); n];
        for r in &self.recent {
            for (i, a) in agree.iter_mut().enumerate() {
                for k in 0..l {
                    let rep = r.reports[i * l + k];
                    if rep <= 1 {
                        a.1 += 1;
                        a.0 += (rep == r.pred.get(k).copied().unwrap_or(0)) as u64;
                    }
                }
            }
        }
        agree.iter().map(|&(a, t)| ratio(a, t)).collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cfg() -> UiSection {
        UiSection {
            history_points: 8,
            drift_window: 3,
            drift_threshold: 0.1,
            reliability_window: 4,
            calibration_window: 2,
            recent_rounds: 3,
            ..UiSection::default()
        }
    }

    fn round(present: &[bool], reports: &[u8]) -> Round {
        Round {
            context: vec![1.0],
            present: present.to_vec(),
            reports: reports.to_vec(),
        }
    }

    #[test]
    fn the_history_is_thinned_evenly_and_ends_at_the_latest_event() {
        let mut d = Dashboard::new(cfg(), 2, 1);
        let r = round(&[true, true], &[1, 0]);
        for t in 1..=100u64 {
            d.on_feedback(t, "r", &r, &[1], &[0.9], &[0.1, 0.0], &[0.5, 0.5]);
        }
        let h = d.history();
        assert!(h.len() <= 9, "{}", h.len());
        assert_eq!(h.first().unwrap().labelled, 1);
        assert_eq!(h.last().unwrap().labelled, 100);
        let steps: Vec<u64> = h
            .windows(2)
            .map(|w| w[1].labelled - w[0].labelled)
            .collect();
        let stride = steps[0];
        assert!(
            steps[..steps.len() - 1].iter().all(|&s| s == stride),
            "{steps:?}"
        );
    }

    #[test]
    fn a_drop_in_credit_raises_an_alarm_once_and_clears() {
        let cfg = UiSection {
            drift_threshold: 0.15,
            ..cfg()
        };
        let mut d = Dashboard::new(cfg, 2, 1);
        let r = round(&[true, true], &[1, 0]);
        let mut t = 0;
        let mut feed = |d: &mut Dashboard, phi0: f64| {
            t += 1;
            // Reporter 1 keeps a credit of 0.1: reporter 0's share falls from 0.75 to 0.
            d.on_feedback(t, "r", &r, &[1], &[0.9], &[phi0, 0.1], &[0.5, 0.5]);
        };
        for _ in 0..6 {
            feed(&mut d, 0.3);
        }
        assert!(!d.alarm[0]);
        for _ in 0..3 {
            feed(&mut d, 0.0);
        }
        // Shares 0.75, then 0: event 7 a fall of 0.25 > 0.15.
        assert!(d.alarm[0], "a fall of 0.75 > 0.15");
        assert_eq!(d.alarm_at[0].len(), 1);
        for _ in 0..6 {
            feed(&mut d, 0.0);
        }
        assert!(!d.alarm[0], "both windows at 0 again");
        assert_eq!(d.alarm_at[0].iter().copied().collect::<Vec<_>>(), vec![7]);
        assert!(d.alarm_at[1].is_empty(), "reporter 1's share rose");
    }

    #[test]
    fn rates_count_known_labels_of_present_reporters_in_the_window() {
        let mut d = Dashboard::new(cfg(), 2, 2);
        // Reporter 0 says label 0, reporter 1 absent. Truth: label 0 yes, label 1 unknown.
        let r = round(&[true, false], &[1, 1, 0, 0]);
        d.on_feedback(1, "r", &r, &[1, 2], &[0.8, 0.5], &[0.0, 0.0], &[0.5, 0.5]);
        let p = d.panels(&["a".into(), "b".into()]);
        assert_eq!(p.reliability.overall.tpr[0][0], Some(1.0));
        assert_eq!(p.reliability.overall.tpr[0][1], None, "label 1 unknown");
        assert_eq!(p.reliability.overall.tpr[1][0], None, "reporter 1 absent");
        // Four events of "no" push the first out of the window of 4.
        let r2 = round(&[true, false], &[1, 0, 0, 0]);
        for t in 2..=5 {
            d.on_feedback(t, "r", &r2, &[0, 0], &[0.3, 0.1], &[0.0, 0.0], &[0.5, 0.5]);
        }
        let p = d.panels(&["a".into(), "b".into()]);
        assert_eq!(p.reliability.overall.rounds, 4);
        assert_eq!(
            p.reliability.overall.tpr[0][0], None,
            "the positive left the window"
        );
        assert_eq!(p.reliability.overall.fpr[0][0], Some(1.0));
        assert_eq!(p.reliability.overall.fpr[0][1], Some(0.0));
        // Calibration over the latest 2: q 0.3 (y 0) and 0.1 (y 0) twice.
        assert_eq!(p.calibration.pairs, 4);
        let ece = p.calibration.ece.unwrap();
        assert!((ece - 0.2).abs() < 1e-12, "{ece}");
    }

    #[test]
    fn percentiles_are_nearest_rank() {
        let s: Vec<f64> = (1..=100).map(f64::from).collect();
        assert_eq!(percentile(&s, 0.5), Some(50.0));
        assert_eq!(percentile(&s, 0.99), Some(99.0));
        assert_eq!(percentile(&[], 0.5), None);
    }
}
