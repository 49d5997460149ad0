//! The learning-curve protocol of `eval --labelled N` / `--curve` and the unsupervised
//! Dawid–Skene baseline it is compared with. No I/O.

use crate::metrics::{MetricsAcc, Scores};
use crate::replay::ParsedRound;
use rand::seq::SliceRandom;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

/// The history rounds with a truth and how many of them keep it, or `Err(count)` when all of
/// them do (`keep` is `None` or not below their count): the part both choices share.
fn to_hide(
    rounds: &[ParsedRound],
    n_hist: usize,
    keep: Option<usize>,
) -> Result<(Vec<usize>, usize), usize> {
    let labelled: Vec<usize> = (0..n_hist.min(rounds.len()))
        .filter(|&t| rounds[t].truth.is_some())
        .collect();
    match keep {
        Some(k) if k < labelled.len() => Ok((labelled, k)),
        _ => Err(labelled.len()),
    }
}

/// `rounds` in the order `seed` shuffles them: its first k are the seed's uniform draw of k, the
/// same draw for random picks and for the review queue's pool.
fn seeded_order(rounds: &[usize], seed: u64) -> Vec<usize> {
    let mut order = rounds.to_vec();
    order.shuffle(&mut ChaCha8Rng::seed_from_u64(seed));
    order
}

/// Keeps the truth of `keep` history rounds (all of them for `None`), chosen uniformly among the
/// history rounds that have one by `seed`, and hides the others'. Test rounds (after the first
/// `n_hist`) keep their truth: they are scored on it. Returns the rounds and how many history
/// rounds kept their truth.
pub fn hide_labels(
    rounds: &[ParsedRound],
    n_hist: usize,
    keep: Option<usize>,
    seed: u64,
) -> (Vec<ParsedRound>, usize) {
    let mut out = rounds.to_vec();
    let (labelled, keep) = match to_hide(rounds, n_hist, keep) {
        Ok(v) => v,
        Err(all) => return (out, all),
    };
    for &t in &seeded_order(&labelled, seed)[keep..] {
        out[t].truth = None;
    }
    (out, keep)
}

/// Which history rounds the review queue may pick from: all of them, or a share chosen by a
/// seed (`eval --review-pool`).
///
/// The queue is deterministic, so one queue is one sample of N rounds, and comparing it with
/// random picks compares one draw against many: a draw of 50 labels moves micro-F1 by a standard
/// deviation of up to 0.04 on the benchmark suite. Ranking over a seeded share of the rounds (as
/// the service ranks over a window of the latest ones) gives the queue a distribution of
/// outcomes too, to be averaged over seeds like random picks.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ReviewPool {
    /// Share of the history rounds with a truth that are candidates, in (0, 1].
    pub share: f64,
    /// Chooses them when `share < 1`.
    pub seed: u64,
}

impl ReviewPool {
    /// Every history round is a candidate.
    pub const ALL: ReviewPool = ReviewPool {
        share: 1.0,
        seed: 0,
    };
}

/// Like [`hide_labels`], but the `keep` history rounds that keep their truth are the review
/// queue's first `keep` ([`crate::review`]) over the `pool`'s candidates, ranked on what is known
/// without any truth: the unsupervised posteriors `q` (one row per round, e.g.
/// [`dawid_skene`]'s), the reporters' disagreement and the novelty of each context. A pool
/// smaller than `keep` gives all its rounds.
pub fn pick_review(
    rounds: &[ParsedRound],
    n_hist: usize,
    keep: Option<usize>,
    q: &[Vec<f64>],
    pool: ReviewPool,
) -> (Vec<ParsedRound>, usize) {
    let mut out = rounds.to_vec();
    let (labelled, keep) = match to_hide(rounds, n_hist, keep) {
        Ok(v) => v,
        Err(all) => return (out, all),
    };
    let l = q.first().map_or(0, Vec::len);
    let pooled = if pool.share < 1.0 {
        let size = ((pool.share.max(0.0) * labelled.len() as f64).ceil() as usize).max(1);
        let mut pooled = seeded_order(&labelled, pool.seed);
        pooled.truncate(size);
        // Time order, as the queue sees the service's window: ties go to the older round.
        pooled.sort_unstable();
        pooled
    } else {
        labelled.clone()
    };
    let cands: Vec<crate::review::Candidate> = pooled
        .iter()
        .map(|&t| crate::review::Candidate {
            seq: t as u64,
            context: rounds[t].round.context.clone(),
            present: rounds[t].round.present.clone(),
            reports: rounds[t].round.reports.clone(),
            q: q[t].clone(),
            known: vec![false; l],
        })
        .collect();
    let picked: std::collections::HashSet<u64> = crate::review::rank(&cands, &[], l, keep)
        .into_iter()
        .map(|p| p.seq)
        .collect();
    for &t in &labelled {
        if !picked.contains(&(t as u64)) {
            out[t].truth = None;
        }
    }
    (out, picked.len())
}

/// Binary-relevance Dawid–Skene (Dawid & Skene 1979), fitted without any truth on every round of
/// the file: per reporter and label a 2x2 confusion matrix and per label a class prior, EM from
/// the majority-vote initialisation, as crowd-kit's `BinaryRelevance(DawidSkene)` does. Context
/// is ignored. Returns `P(y_k = 1)` per round and label. `smoothing` is added to every confusion
/// count (keeps a reporter that never said "yes" from producing log 0).
pub fn dawid_skene(
    rounds: &[ParsedRound],
    n: usize,
    l: usize,
    iters: usize,
    smoothing: f64,
) -> Vec<Vec<f64>> {
    let m = rounds.len();
    // Initial posteriors: the share of present reporters that report the label.
    let mut post: Vec<Vec<f64>> = rounds
        .iter()
        .map(|r| {
            let present = r.round.present.iter().filter(|&&p| p).count().max(1) as f64;
            (0..l)
                .map(|k| {
                    (0..n)
                        .filter(|&i| r.round.present[i] && r.round.reports[i * l + k] != 0)
                        .count() as f64
                        / present
                })
                .collect()
        })
        .collect();
    for _ in 0..iters {
        // M-step: per reporter and label, P(r = 1 | y = 1) and P(r = 1 | y = 0); class priors.
        let mut c = vec![[smoothing; 4]; n * l]; // [r1y1, r0y1, r1y0, r0y0]
        let mut prior = vec![0.0; l];
        for (r, p) in rounds.iter().zip(&post) {
            for k in 0..l {
                prior[k] += p[k];
                for i in 0..n {
                    if !r.round.present[i] {
                        continue;
                    }
                    let cell = &mut c[i * l + k];
                    if r.round.reports[i * l + k] != 0 {
                        cell[0] += p[k];
                        cell[2] += 1.0 - p[k];
                    } else {
                        cell[1] += p[k];
                        cell[3] += 1.0 - p[k];
                    }
                }
            }
        }
        // Log-likelihood ratios of a "yes" and a "no" per reporter and label, and the priors.
        let mut llr = vec![(0.0f64, 0.0f64); n * l];
        for (v, cell) in llr.iter_mut().zip(&c) {
            let tp = cell[0] / (cell[0] + cell[1]);
            let fp = cell[2] / (cell[2] + cell[3]);
            *v = ((tp / fp).ln(), ((1.0 - tp) / (1.0 - fp)).ln());
        }
        let prior_logit: Vec<f64> = prior
            .iter()
            .map(|&p| {
                let pi = (p / m as f64).clamp(1e-6, 1.0 - 1e-6);
                (pi / (1.0 - pi)).ln()
            })
            .collect();
        let mut change = 0.0f64;
        // E-step.
        for (r, p) in rounds.iter().zip(post.iter_mut()) {
            for k in 0..l {
                let mut z = prior_logit[k];
                for i in 0..n {
                    if !r.round.present[i] {
                        continue;
                    }
                    let (yes, no) = llr[i * l + k];
                    z += if r.round.reports[i * l + k] != 0 {
                        yes
                    } else {
                        no
                    };
                }
                let q = crate::signals::sigmoid(z);
                change = change.max((q - p[k]).abs());
                p[k] = q;
            }
        }
        if change < 1e-7 {
            break;
        }
    }
    post
}

/// Scores posteriors given per round (e.g. [`dawid_skene`]'s) on the scored rounds, predicting a
/// label when its posterior exceeds 1/2.
pub fn score_posteriors(
    rounds: &[ParsedRound],
    post: &[Vec<f64>],
    n_hist: usize,
    l: usize,
    eps: f64,
) -> Scores {
    let mut acc = MetricsAcc::new(l, eps);
    for (r, p) in rounds.iter().zip(post).skip(n_hist) {
        if let Some(truth) = &r.truth {
            let pred: Vec<u8> = p.iter().map(|&q| (q > 0.5) as u8).collect();
            acc.add(&pred, p, truth, None);
        }
    }
    acc.finish()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::Round;

    fn round(present: Vec<bool>, reports: Vec<u8>, truth: Option<Vec<u8>>) -> ParsedRound {
        ParsedRound {
            line: 0,
            id: String::new(),
            round: Round {
                context: vec![1.0],
                present,
                reports,
            },
            truth,
        }
    }

    #[test]
    fn hiding_keeps_exactly_n_history_labels_and_every_test_label() {
        let rounds: Vec<ParsedRound> = (0..100)
            .map(|t| {
                round(
                    vec![true],
                    vec![0],
                    if t % 10 == 3 { None } else { Some(vec![1]) },
                )
            })
            .collect();
        let (h, kept) = hide_labels(&rounds, 70, Some(12), 5);
        assert_eq!(kept, 12);
        assert_eq!(h[..70].iter().filter(|r| r.truth.is_some()).count(), 12);
        assert!(h[70..]
            .iter()
            .zip(&rounds[70..])
            .all(|(a, b)| a.truth == b.truth));
        let (again, _) = hide_labels(&rounds, 70, Some(12), 5);
        assert!(h.iter().zip(&again).all(|(a, b)| a.truth == b.truth));
        let (other, _) = hide_labels(&rounds, 70, Some(12), 6);
        assert!(h.iter().zip(&other).any(|(a, b)| a.truth != b.truth));
        let (all, kept) = hide_labels(&rounds, 70, None, 5);
        assert_eq!(kept, 63);
        assert!(all.iter().zip(&rounds).all(|(a, b)| a.truth == b.truth));
    }

    #[test]
    fn the_review_pick_keeps_the_disputed_rounds_and_every_test_label() {
        // Rounds 0..70 are history, their contexts spread along an arc; those with t % 7 == 0
        // are disputed (the two reporters disagree) and uncertain (q = 0.5), the rest unanimous
        // and sure. The queue spreads its ten picks over the arc and leans to disputed rounds.
        let rounds: Vec<ParsedRound> = (0..100)
            .map(|t| {
                let reports = if t % 7 == 0 { vec![1, 0] } else { vec![1, 1] };
                let mut r = round(vec![true, true], reports, Some(vec![1]));
                r.round.context = vec![1.0, t as f64 / 100.0];
                let n = r.round.context.iter().map(|v| v * v).sum::<f64>().sqrt();
                r.round.context.iter_mut().for_each(|v| *v /= n);
                r
            })
            .collect();
        let q: Vec<Vec<f64>> = (0..100)
            .map(|t| vec![if t % 7 == 0 { 0.5 } else { 0.99 }])
            .collect();
        let (h, kept) = pick_review(&rounds, 70, Some(10), &q, ReviewPool::ALL);
        assert_eq!(kept, 10);
        let picked: Vec<usize> = (0..70).filter(|&t| h[t].truth.is_some()).collect();
        assert_eq!(picked.len(), 10);
        let gaps = picked.windows(2).map(|w| w[1] - w[0]);
        assert!(
            gaps.max().unwrap() <= 14 && picked[0] <= 7 && picked[9] >= 62,
            "{picked:?}"
        );
        // Uniform picks would hold 10/7 of the disputed rounds on average.
        assert!(
            picked.iter().filter(|t| *t % 7 == 0).count() >= 2,
            "{picked:?}"
        );
        assert!(h[70..].iter().all(|r| r.truth.is_some()));
        let (all, kept) = pick_review(&rounds, 70, None, &q, ReviewPool::ALL);
        assert_eq!(kept, 70);
        assert!(all.iter().all(|r| r.truth.is_some()));
    }

    #[test]
    fn a_review_pool_picks_only_from_its_seeded_share() {
        let rounds: Vec<ParsedRound> = (0..100)
            .map(|t| {
                let mut r = round(vec![true, true], vec![1, (t % 3 == 0) as u8], Some(vec![1]));
                let a = t as f64 / 30.0;
                r.round.context = vec![a.cos(), a.sin()];
                r
            })
            .collect();
        let q: Vec<Vec<f64>> = (0..100).map(|_| vec![0.7]).collect();
        let kept = |h: &[ParsedRound]| -> Vec<usize> {
            (0..70).filter(|&t| h[t].truth.is_some()).collect()
        };
        let pool = |seed| ReviewPool { share: 0.3, seed };
        let (a, n) = pick_review(&rounds, 70, Some(10), &q, pool(1));
        assert_eq!(n, 10);
        // The pool is the seed's 21 of the 70 history rounds, as hide_labels would keep them.
        let (members, _) = hide_labels(&rounds, 70, Some(21), 1);
        let members = kept(&members);
        assert!(
            kept(&a).iter().all(|t| members.contains(t)),
            "{:?}",
            kept(&a)
        );
        assert!(a[70..].iter().all(|r| r.truth.is_some()));
        // Deterministic per seed, another seed another pool; the whole pool is the plain queue.
        assert_eq!(
            kept(&a),
            kept(&pick_review(&rounds, 70, Some(10), &q, pool(1)).0)
        );
        assert_ne!(
            kept(&a),
            kept(&pick_review(&rounds, 70, Some(10), &q, pool(2)).0)
        );
        let whole = ReviewPool {
            share: 1.0,
            seed: 9,
        };
        assert_eq!(
            kept(&pick_review(&rounds, 70, Some(10), &q, whole).0),
            kept(&pick_review(&rounds, 70, Some(10), &q, ReviewPool::ALL).0)
        );
        // A pool smaller than N gives all of it.
        let (small, n) = pick_review(
            &rounds,
            70,
            Some(10),
            &q,
            ReviewPool {
                share: 0.1,
                seed: 1,
            },
        );
        assert_eq!(n, 7);
        assert_eq!(kept(&small).len(), 7);
    }

    #[test]
    fn dawid_skene_finds_the_reliable_reporter() {
        // Reporter 0 is right 95% of the time, reporter 1 85%, reporter 2 is a coin: DS should
        // learn to ignore the coin. (With two coins against one good reporter the vote-share
        // start is symmetric enough that EM may settle on the coins: a known local optimum of
        // Dawid-Skene, not something this baseline claims to avoid.)
        let mut s = 3u64;
        let mut f = || {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (s >> 11) as f64 / (1u64 << 53) as f64
        };
        let mut rounds = Vec::new();
        for _ in 0..600 {
            let y = (f() < 0.3) as u8;
            let r0 = y ^ (f() < 0.05) as u8;
            let r1 = y ^ (f() < 0.15) as u8;
            let r2 = (f() < 0.5) as u8;
            rounds.push(round(vec![true; 3], vec![r0, r1, r2], Some(vec![y])));
        }
        let post = dawid_skene(&rounds, 3, 1, 100, 0.01);
        let s = score_posteriors(&rounds, &post, 0, 1, 1e-6);
        assert!(s.hamming < 0.08, "{}", s.hamming);
    }
}
