//! The review queue: which rounds a person should label next (`GET /v1/review`, `eval --pick
//! review`). No I/O.
//!
//! A person's label teaches the engine most where the engine is least sure of its answer, where
//! the reporters disagree, and where it has seen little like the round before; and only on the
//! labels nobody has given yet (the vehicle's signals settle some: docs/ANNOTATE.md). Each
//! candidate gets
//!
//! - `uncertainty`: the mean over its unknown labels of `1 - |2q - 1|` (1 at q = 0.5, 0 at a
//!   certain 0 or 1), `q` the posterior it was served;
//! - `disagreement`: the mean over its unknown labels of `4 p (1 - p)`, `p` the share of the
//!   present reporters that report the label (1 when they split evenly, 0 when unanimous);
//! - `novelty`: `1 - max cos` between its context and every labelled round's and every round
//!   picked before it in this queue (so the queue spreads over the context space instead of
//!   asking about ten near-copies of one scene);
//!
//! and the queue is built greedily: each step takes the candidate with the highest
//! `(uncertainty + disagreement) / 2 * (novelty_floor + (1 - novelty_floor) * novelty)`, ties to
//! the older round. `novelty_floor` (0.25) keeps a round that is uncertain but close to a
//! labelled one in the running. Work: O(candidates × (picked + labelled) × dim).

use crate::bank::dot;

/// A round that could be labelled.
#[derive(Debug, Clone)]
pub struct Candidate {
    pub seq: u64,
    /// Unit-norm context.
    pub context: Vec<f64>,
    /// One flag per configured reporter.
    pub present: Vec<bool>,
    /// `n * L` reports.
    pub reports: Vec<u8>,
    /// The posteriors it was served.
    pub q: Vec<f64>,
    /// Per label: whether its truth is known already (partial feedback).
    pub known: Vec<bool>,
}

/// A queue entry: the round, its score and the parts it is made of.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Pick {
    pub seq: u64,
    pub score: f64,
    pub uncertainty: f64,
    pub disagreement: f64,
    pub novelty: f64,
    /// Label indices still unknown (what a label would teach).
    pub unknown: Vec<usize>,
}

/// See the module docs.
pub const NOVELTY_FLOOR: f64 = 0.25;

fn parts(c: &Candidate, l: usize) -> Option<(f64, f64, Vec<usize>)> {
    let unknown: Vec<usize> = (0..l).filter(|&k| !c.known[k]).collect();
    if unknown.is_empty() {
        return None;
    }
    let members: Vec<usize> = (0..c.present.len()).filter(|&i| c.present[i]).collect();
    let m = members.len().max(1) as f64;
    let mut unc = 0.0;
    let mut dis = 0.0;
    for &k in &unknown {
        unc += 1.0 - (2.0 * c.q[k] - 1.0).abs();
        let p = members
            .iter()
            .filter(|&&i| c.reports[i * l + k] != 0)
            .count() as f64
            / m;
        dis += 4.0 * p * (1.0 - p);
    }
    let u = unknown.len() as f64;
    Some((unc / u, dis / u, unknown))
}

/// The first `limit` rounds of the queue over `candidates`, given the contexts of the rounds
/// already labelled (`labelled`, unit-norm).
pub fn rank(candidates: &[Candidate], labelled: &[Vec<f64>], l: usize, limit: usize) -> Vec<Pick> {
    let scored: Vec<(usize, f64, f64, Vec<usize>)> = candidates
        .iter()
        .enumerate()
        .filter_map(|(i, c)| parts(c, l).map(|(u, d, unk)| (i, u, d, unk)))
        .collect();
    // Best cosine of each candidate to anything labelled or picked so far.
    let mut near: Vec<f64> = scored
        .iter()
        .map(|(i, ..)| {
            labelled
                .iter()
                .map(|x| dot(&candidates[*i].context, x))
                .fold(-1.0, f64::max)
        })
        .collect();
    let mut taken = vec![false; scored.len()];
    let mut out = Vec::with_capacity(limit.min(scored.len()));
    while out.len() < limit {
        let mut best: Option<(usize, f64, f64)> = None;
        for (j, (i, u, d, _)) in scored.iter().enumerate() {
            if taken[j] {
                continue;
            }
            let novelty = (1.0 - near[j]).clamp(0.0, 1.0);
            let s = (u + d) / 2.0 * (NOVELTY_FLOOR + (1.0 - NOVELTY_FLOOR) * novelty);
            let better = match best {
                None => true,
                Some((bj, bs, _)) => {
                    s > bs || (s == bs && candidates[*i].seq < candidates[scored[bj].0].seq)
                }
            };
            if better {
                best = Some((j, s, novelty));
            }
        }
        let Some((j, s, novelty)) = best else { break };
        taken[j] = true;
        let (i, u, d, unk) = &scored[j];
        let x = &candidates[*i].context;
        for (jj, (ii, ..)) in scored.iter().enumerate() {
            if !taken[jj] {
                near[jj] = near[jj].max(dot(&candidates[*ii].context, x));
            }
        }
        out.push(Pick {
            seq: candidates[*i].seq,
            score: s,
            uncertainty: *u,
            disagreement: *d,
            novelty,
            unknown: unk.clone(),
        });
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cand(seq: u64, ctx: [f64; 2], q: f64, reports: [u8; 2]) -> Candidate {
        let n = (ctx[0] * ctx[0] + ctx[1] * ctx[1]).sqrt();
        Candidate {
            seq,
            context: vec![ctx[0] / n, ctx[1] / n],
            present: vec![true, true],
            reports: reports.to_vec(),
            q: vec![q],
            known: vec![false],
        }
    }

    #[test]
    fn uncertain_disputed_and_new_rounds_come_first() {
        let c = vec![
            cand(0, [1.0, 0.0], 0.99, [1, 1]), // sure, unanimous
            cand(1, [1.0, 0.01], 0.5, [1, 0]), // unsure, disputed
            cand(2, [1.0, 0.02], 0.5, [1, 0]), // the same scene again
            cand(3, [0.0, 1.0], 0.6, [1, 0]),  // a new scene, slightly less unsure
        ];
        let q = rank(&c, &[], 1, 4);
        let order: Vec<u64> = q.iter().map(|p| p.seq).collect();
        // 1 first (ties in everything with 2 go to the older), then the new scene 3 ahead of
        // 2, whose near-copy is already in the queue; the sure round last.
        assert_eq!(order, vec![1, 3, 2, 0]);
        assert!(q[0].uncertainty == 1.0 && q[0].disagreement == 1.0);
        assert!(q[3].score < q[2].score);
        // A round already labelled near 1 pushes 1 and 2 behind 3.
        let q = rank(&c, &[vec![1.0, 0.0]], 1, 1);
        assert_eq!(q[0].seq, 3);
    }

    #[test]
    fn fully_known_rounds_are_not_asked_for_and_known_labels_do_not_count() {
        let mut a = cand(0, [1.0, 0.0], 0.5, [1, 0]);
        a.known = vec![true];
        let b = cand(1, [0.0, 1.0], 0.9, [1, 1]);
        let q = rank(&[a, b], &[], 1, 5);
        assert_eq!(q.len(), 1);
        assert_eq!(q[0].seq, 1);
        assert_eq!(q[0].unknown, vec![0]);
    }
}
