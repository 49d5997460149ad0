//! Which predictor serves (docs/METHOD.md §3, `serve = "switch"`): the one whose decisions,
//! scored on each labelled round before its label is learned, have the lowest recent loss.
//!
//! Four candidates decide every round: the whole-pool Dawid–Skene ([`super::ds`]), the
//! context-aware model (the method's calibrated posteriors and fitted thresholds), majority
//! vote, and the paper method's rule over the latest labelled rounds ([`super::paper`]; left out
//! with `paper_window = 0`). Each labelled round adds to every candidate's loss `FP + c FN` over the round's known
//! labels (`c = switch_fn_cost`: a missed label costs more than a false alarm, as micro-F1 has
//! it), after discounting the loss so far by `switch_discount` (a window of about `1 / (1 -
//! discount)` labelled rounds, so that a candidate that turns worse, as under drift, is left).
//! The serving candidate changes only when another's loss is lower than its own by more than
//! `switch_margin`: follow the leader with a hysteresis, so the served loss exceeds the best
//! candidate's by at most the margin between switches, and a tie never flips the choice. With no
//! label every loss is zero and the first candidate, Dawid–Skene, serves; it keeps serving until
//! `switch_min_rounds` labelled rounds have been scored (a loss gap over a handful of rounds is
//! mostly noise). The model/paper mean's loss is compared at `1 - switch_mean_edge` times its
//! value: averaging two partly independent learners helps more than their scores while they
//! were still learning show.

use serde::{Deserialize, Serialize};

/// A candidate predictor.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Predictor {
    /// The whole-pool Dawid–Skene posterior, decided at `threshold_initial`.
    DawidSkene,
    /// The context-aware model: calibrated posteriors at the fitted thresholds.
    Model,
    /// Majority vote.
    MajorityVote,
    /// PAPER-METHOD.md's rule (labelled neighbours only, Beta reliabilities, guardrail window)
    /// over the pool's latest `paper_window` labelled rounds, at its own fitted thresholds.
    Paper,
    /// The mean of the model's and the `paper` candidate's posteriors, at the mean of their
    /// thresholds.
    #[serde(rename = "model_paper_mean")]
    Blend,
}

/// How many candidates the switch keeps a score for.
pub const CANDIDATES: usize = 5;

impl Predictor {
    /// Every candidate, in the order ties are broken.
    pub const ALL: [Predictor; CANDIDATES] = [
        Predictor::DawidSkene,
        Predictor::Model,
        Predictor::MajorityVote,
        Predictor::Paper,
        Predictor::Blend,
    ];

    /// Whether the candidate needs the `paper` candidate (left out with `paper_window = 0`).
    pub fn needs_paper(self) -> bool {
        matches!(self, Predictor::Paper | Predictor::Blend)
    }

    /// The name responses, `/v1/state`, `/metrics` and the operator page give it.
    pub fn name(self) -> &'static str {
        match self {
            Predictor::DawidSkene => "dawid_skene",
            Predictor::Model => "model",
            Predictor::MajorityVote => "majority_vote",
            Predictor::Paper => "paper",
            Predictor::Blend => "model_paper_mean",
        }
    }

    fn index(self) -> usize {
        self as usize
    }
}

/// Discounted decision counts of one candidate.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct Counts {
    pub tp: f64,
    pub fp: f64,
    pub fneg: f64,
}

impl Counts {
    /// Micro-F1 of the discounted counts (1 with no positive at all).
    pub fn f1(&self) -> f64 {
        let den = 2.0 * self.tp + self.fp + self.fneg;
        if den == 0.0 {
            1.0
        } else {
            2.0 * self.tp / den
        }
    }
}

/// One candidate's recent score, as `/v1/state` and `/metrics` show it.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct CandidateScore {
    pub predictor: Predictor,
    /// The discounted loss the switch compares (`FP + switch_fn_cost * FN`).
    pub loss: f64,
    /// Discounted Hamming errors (FP + FN).
    pub errors: f64,
    /// Micro-F1 of the discounted counts.
    pub micro_f1: f64,
}

/// The switch's constants (docs/METHOD.md §3; `switch_*` in the configuration).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SwitchRule {
    /// What each candidate's loss so far is multiplied by before a labelled round adds to it.
    pub discount: f64,
    /// What a missed label costs, against 1 for a false alarm.
    pub fn_cost: f64,
    /// How much lower another candidate's loss must be before it serves.
    pub margin: f64,
    /// Labelled rounds scored before the serving candidate may change.
    pub min_rounds: u64,
    /// The model/paper mean's loss is compared at `1 - mean_edge` times its value.
    pub mean_edge: f64,
}

/// The switch's state.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Switch {
    loss: [f64; CANDIDATES],
    counts: [Counts; CANDIDATES],
    serving: Predictor,
    /// Labelled rounds scored.
    rounds: u64,
}

impl Default for Switch {
    fn default() -> Self {
        Self {
            loss: [0.0; CANDIDATES],
            counts: [Counts::default(); CANDIDATES],
            serving: Predictor::DawidSkene,
            rounds: 0,
        }
    }
}

impl Switch {
    /// The candidate serving now.
    pub fn serving(&self) -> Predictor {
        self.serving
    }

    /// Scores one labelled round: `decisions[c][k]` is candidate `c`'s decision (in
    /// [`Predictor::ALL`] order) on label `k`, `truth[k]` 0, 1 or unknown (> 1, skipped); a
    /// candidate given no decisions (an empty list: one left out by the configuration) is
    /// neither scored nor chosen. Then, once `min_rounds` labelled rounds have been scored (or
    /// sooner when `early()` says so, asked only before then: the labelled rounds already show two
    /// reporters erring together, which breaks the independence Dawid–Skene's agreement-based
    /// reliabilities rest on), the serving candidate is chosen again.
    pub fn score(
        &mut self,
        decisions: &[Vec<bool>; CANDIDATES],
        truth: &[u8],
        rule: &SwitchRule,
        early: impl FnOnce() -> bool,
    ) {
        let SwitchRule {
            discount,
            fn_cost,
            margin,
            min_rounds,
            mean_edge,
        } = *rule;
        for (c, dec) in decisions.iter().enumerate() {
            if dec.is_empty() {
                continue;
            }
            let (mut fp, mut fneg, mut tp) = (0.0, 0.0, 0.0);
            for (&d, &y) in dec.iter().zip(truth) {
                match (d, y) {
                    (_, y) if y > 1 => {}
                    (true, 1) => tp += 1.0,
                    (true, _) => fp += 1.0,
                    (false, 1) => fneg += 1.0,
                    _ => {}
                }
            }
            self.loss[c] = discount * self.loss[c] + fp + fn_cost * fneg;
            let k = &mut self.counts[c];
            k.tp = discount * k.tp + tp;
            k.fp = discount * k.fp + fp;
            k.fneg = discount * k.fneg + fneg;
        }
        self.rounds += 1;
        if self.rounds < min_rounds && !early() {
            return;
        }
        // What the switch compares: the loss, the mean's shrunk by its edge.
        let eff = |c: usize| {
            if c == Predictor::Blend.index() {
                self.loss[c] * (1.0 - mean_edge)
            } else {
                self.loss[c]
            }
        };
        // The leader: the lowest, ties to the earlier candidate.
        let mut best = 0;
        for (c, dec) in decisions.iter().enumerate().skip(1) {
            if !dec.is_empty() && eff(c) < eff(best) {
                best = c;
            }
        }
        if eff(best) < eff(self.serving.index()) - margin {
            self.serving = Predictor::ALL[best];
        }
    }

    /// The recent score of every candidate in play (`paper` only when `with_paper`).
    pub fn scores(&self, with_paper: bool) -> Vec<CandidateScore> {
        Predictor::ALL
            .iter()
            .filter(|&&p| with_paper || !p.needs_paper())
            .map(|&p| {
                let c = self.counts[p.index()];
                CandidateScore {
                    predictor: p,
                    loss: self.loss[p.index()],
                    errors: c.fp + c.fneg,
                    micro_f1: c.f1(),
                }
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rule(discount: f64, fn_cost: f64, margin: f64, min_rounds: u64) -> SwitchRule {
        SwitchRule {
            discount,
            fn_cost,
            margin,
            min_rounds,
            mean_edge: 0.0,
        }
    }

    fn dec(v: &[u8]) -> Vec<bool> {
        v.iter().map(|&b| b != 0).collect()
    }

    #[test]
    fn serves_dawid_skene_until_another_candidate_leads_by_the_margin() {
        let mut s = Switch::default();
        assert_eq!(s.serving(), Predictor::DawidSkene);
        let truth = [1u8, 0, 1, 0];
        // The model is right, Dawid-Skene misses one label a round, the vote two.
        let d = [
            dec(&[0, 0, 1, 0]),
            dec(&[1, 0, 1, 0]),
            dec(&[0, 1, 1, 0]),
            Vec::new(),
            Vec::new(),
        ];
        s.score(&d, &truth, &rule(1.0, 1.5, 3.0, 0), || false);
        // Loss 1.5 against 0: within the margin, no switch.
        assert_eq!(s.serving(), Predictor::DawidSkene);
        s.score(&d, &truth, &rule(1.0, 1.5, 3.0, 0), || false);
        s.score(&d, &truth, &rule(1.0, 1.5, 3.0, 0), || false);
        // 4.5 against 0: past it.
        assert_eq!(s.serving(), Predictor::Model);
        let sc = s.scores(false);
        assert_eq!(sc.len(), 3);
        assert_eq!(sc[0].loss, 4.5);
        assert_eq!(sc[2].errors, 6.0);
        assert_eq!(sc[1].micro_f1, 1.0);
        assert_eq!(s.rounds, 3);
    }

    #[test]
    fn unknown_labels_are_not_scored_and_discounting_forgets() {
        let mut s = Switch::default();
        let d = [
            dec(&[1, 1]),
            dec(&[0, 0]),
            dec(&[0, 0]),
            Vec::new(),
            Vec::new(),
        ];
        // The second label is unknown: only the first counts.
        s.score(&d, &[0, 2], &rule(0.5, 1.0, 0.0, 0), || false);
        assert_eq!(s.scores(false)[0].loss, 1.0);
        assert_eq!(s.serving(), Predictor::Model);
        s.score(&d, &[0, 2], &rule(0.5, 1.0, 0.0, 0), || false);
        assert_eq!(s.scores(false)[0].loss, 1.5);
    }

    #[test]
    fn the_paper_candidate_serves_when_it_leads_and_never_when_left_out() {
        let truth = [1u8, 0, 1, 0];
        let right = dec(&[1, 0, 1, 0]);
        let wrong = dec(&[0, 1, 0, 1]);
        let mut s = Switch::default();
        for _ in 0..2 {
            s.score(
                &[
                    wrong.clone(),
                    wrong.clone(),
                    wrong.clone(),
                    right.clone(),
                    wrong.clone(),
                ],
                &truth,
                &rule(1.0, 1.0, 3.0, 0),
                || false,
            );
        }
        assert_eq!(s.serving(), Predictor::Paper);
        assert_eq!(s.scores(true)[3].predictor, Predictor::Paper);
        assert_eq!(s.scores(true)[3].errors, 0.0);
        // Left out: its (empty) decisions are not scored, and it is never chosen, even though
        // its loss, never added to, is the lowest.
        let mut s = Switch::default();
        for _ in 0..3 {
            s.score(
                &[
                    wrong.clone(),
                    right.clone(),
                    wrong.clone(),
                    Vec::new(),
                    Vec::new(),
                ],
                &truth,
                &rule(1.0, 1.0, 3.0, 0),
                || false,
            );
        }
        assert_eq!(s.serving(), Predictor::Model);
        assert_eq!(s.scores(false).len(), 3);
        // The wire name is the one `name` gives.
        for p in Predictor::ALL {
            assert_eq!(serde_json::to_value(p).unwrap(), p.name());
        }
    }

    #[test]
    fn nothing_changes_before_min_rounds_labelled_rounds() {
        let truth = [1u8, 0, 1, 0];
        // The model is right and Dawid-Skene wrong on every label: a loss gap of 5 a round.
        let d = [
            dec(&[0, 1, 0, 1]),
            dec(&[1, 0, 1, 0]),
            dec(&[0, 1, 0, 1]),
            Vec::new(),
            Vec::new(),
        ];
        let mut s = Switch::default();
        for _ in 0..4 {
            s.score(&d, &truth, &rule(1.0, 1.5, 3.0, 5), || false);
            assert_eq!(s.serving(), Predictor::DawidSkene);
        }
        // With `early` (dependent reporters' errors) the margin alone decides from the start.
        let mut e = Switch::default();
        e.score(&d, &truth, &rule(1.0, 1.5, 3.0, 5), || true);
        assert_eq!(e.serving(), Predictor::Model);
        // Scored all along: the fifth round switches on the whole gap.
        assert_eq!(s.scores(false)[0].loss, 20.0);
        s.score(&d, &truth, &rule(1.0, 1.5, 3.0, 5), || false);
        assert_eq!(s.serving(), Predictor::Model);
    }

    #[test]
    fn the_mean_is_compared_at_its_edge() {
        let truth = [1u8, 0, 1, 0];
        // The model misses one label a round (loss 1.5); the others but the mean are always
        // wrong.
        let wrong = dec(&[0, 1, 0, 1]);
        let model = dec(&[1, 0, 0, 0]);
        let with_mean = |mean: Vec<bool>| {
            [
                wrong.clone(),
                model.clone(),
                wrong.clone(),
                wrong.clone(),
                mean,
            ]
        };
        let mut s = Switch::default();
        let mut r = rule(1.0, 1.5, 0.0, 0);
        r.mean_edge = 0.5;
        // The mean: a false alarm (loss 1) every other round.
        for i in 0..4 {
            let mean = if i % 2 == 0 {
                &[1, 1, 1, 0]
            } else {
                &[1, 0, 1, 0]
            };
            s.score(&with_mean(dec(mean)), &truth, &r, || false);
        }
        // Losses: model 6, mean 2 (compared at 1): the mean serves.
        assert_eq!(s.serving(), Predictor::Blend);
        assert_eq!(s.scores(true)[4].loss, 2.0);
        // A mean that is worse than the model by less than its edge still wins; by more, not.
        let d = with_mean(dec(&[1, 1, 0, 0])); // loss 2.5 a round against the model's 1.5
        let mut s = Switch::default();
        r.mean_edge = 0.5; // 2.5 * 0.5 = 1.25 < 1.5
        s.score(&d, &truth, &r, || false);
        assert_eq!(s.serving(), Predictor::Blend);
        let mut s = Switch::default();
        r.mean_edge = 0.3; // 2.5 * 0.7 = 1.75 > 1.5
        s.score(&d, &truth, &r, || false);
        assert_eq!(s.serving(), Predictor::Model);
    }
}
