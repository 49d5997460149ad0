//! The method's invariants (PAPER-METHOD.md §4 and the brief): Shapley efficiency, symmetry and the null
//! player; weights summing to 1; the empty bank giving no signal; each ablation switching off
//! exactly its part; and validation that changes nothing.

// Indices mirror the formulas of docs/PAPER-METHOD.md on purpose: a naive transcription is the point.
#![allow(clippy::needless_range_loop, clippy::type_complexity)]

mod common;

use common::{record, Lcg};
use vlmfuse_fusion::{
    reputation_update, Ablations, Engine, FusionConfig, FusionError, LabelledRound, Ontology,
    Round, RoundRecord, ShapleyMethod, Signals,
};

fn random_signals(g: &mut Lcg, p: usize, l: usize) -> Signals {
    let mut rho = vec![0.0; p * p * l];
    for a in 0..p {
        for b in a + 1..p {
            for k in 0..l {
                let r = 0.9 * g.f();
                rho[(a * p + b) * l + k] = r;
                rho[(b * p + a) * l + k] = r;
            }
        }
    }
    let w: Vec<f64> = (0..p).map(|_| 0.2 + g.f()).collect();
    let s: f64 = w.iter().sum();
    Signals {
        l,
        coalition: (0..p).collect(),
        theta_pos: (0..p * l).map(|_| g.f()).collect(),
        theta_neg: (0..p * l).map(|_| g.f()).collect(),
        rho,
        prior: (0..l).map(|_| g.f()).collect(),
        reports: (0..p * l).map(|_| (g.f() < 0.4) as u8).collect(),
        w: w.iter().map(|x| x / s).collect(),
        eps: 1e-6,
    }
}

#[test]
fn shapley_efficiency_holds_to_1e9_exact_and_sampled() {
    let mut g = Lcg(9);
    for p in 1..=10 {
        let s = random_signals(&mut g, p, 14);
        let y: Vec<u8> = (0..14).map(|_| (g.f() < 0.3) as u8).collect();
        let c = s.shapley_exact(&y);
        let sum: f64 = c.phi.iter().sum();
        assert!(
            (sum - c.v_full).abs() < 1e-9,
            "p={p}: {sum} vs {}",
            c.v_full
        );
        // v(N) computed independently of the subset table.
        let lam = s.llr();
        let lp = s.prior_logit();
        let v_full = s.value(&lam, &lp, &y, &|_| true);
        assert!((v_full - c.v_full).abs() < 1e-12);
    }
    // Above the exact limit, sampled permutations telescope: efficiency still holds.
    let s = random_signals(&mut g, 18, 14);
    let y: Vec<u8> = (0..14).map(|_| (g.f() < 0.3) as u8).collect();
    let c = s.shapley_sampled(&y, 300, 1);
    let sum: f64 = c.phi.iter().sum();
    assert!((sum - c.v_full).abs() < 1e-9);
    let lam = s.llr();
    let lp = s.prior_logit();
    assert!((c.v_full - s.value(&lam, &lp, &y, &|_| true)).abs() < 1e-9);
}

#[test]
fn sampled_shapley_agrees_with_exact_within_its_stated_error() {
    let mut g = Lcg(21);
    let s = random_signals(&mut g, 6, 14);
    let y: Vec<u8> = (0..14).map(|_| (g.f() < 0.3) as u8).collect();
    let exact = s.shapley_exact(&y);
    let sampled = s.shapley_sampled(&y, 4000, 77);
    let ShapleyMethod::Sampled { std_error, samples } = &sampled.method else {
        panic!("expected sampled")
    };
    assert_eq!(*samples, 4000);
    for a in 0..6 {
        let z = (sampled.phi[a] - exact.phi[a]).abs() / std_error[a].max(1e-12);
        assert!(
            z < 5.0,
            "member {a}: {} vs {} (se {})",
            sampled.phi[a],
            exact.phi[a],
            std_error[a]
        );
    }
    // Same seed, same draw: a replay credits identically.
    assert_eq!(sampled, s.shapley_sampled(&y, 4000, 77));
}

#[test]
fn symmetric_members_get_equal_credit() {
    let mut g = Lcg(5);
    let mut s = random_signals(&mut g, 4, 14);
    let l = 14;
    let p = 4;
    // Make members 1 and 2 interchangeable: same theta, reports, weight, and rho to others.
    for k in 0..l {
        s.theta_pos[2 * l + k] = s.theta_pos[l + k];
        s.theta_neg[2 * l + k] = s.theta_neg[l + k];
        s.reports[2 * l + k] = s.reports[l + k];
        for c in [0usize, 3] {
            let r = s.rho[(p + c) * l + k];
            s.rho[(2 * p + c) * l + k] = r;
            s.rho[(c * p + 2) * l + k] = r;
        }
    }
    s.w[2] = s.w[1];
    let y: Vec<u8> = (0..l).map(|_| (g.f() < 0.3) as u8).collect();
    let c = s.shapley_exact(&y);
    assert!((c.phi[1] - c.phi[2]).abs() < 1e-12, "{:?}", c.phi);
    assert!(
        (c.phi[0] - c.phi[1]).abs() > 1e-6,
        "the test must not be trivially symmetric"
    );
}

#[test]
fn a_null_player_gets_zero_and_leaves_the_others_unchanged() {
    let mut g = Lcg(6);
    let mut s = random_signals(&mut g, 4, 14);
    let (l, p) = (14, 4);
    // Member 3 carries no signal (theta+ = theta-) and no correlation with anyone.
    for k in 0..l {
        s.theta_neg[3 * l + k] = s.theta_pos[3 * l + k];
        for b in 0..p {
            s.rho[(3 * p + b) * l + k] = 0.0;
            s.rho[(b * p + 3) * l + k] = 0.0;
        }
    }
    let y: Vec<u8> = (0..l).map(|_| (g.f() < 0.3) as u8).collect();
    let with = s.shapley_exact(&y);
    assert!(with.phi[3].abs() < 1e-12, "null player got {}", with.phi[3]);
    // The game without member 3.
    let mut without = s.clone();
    without.coalition.truncate(3);
    without.theta_pos.truncate(3 * l);
    without.theta_neg.truncate(3 * l);
    without.reports.truncate(3 * l);
    without.w.truncate(3);
    without.rho = vec![0.0; 9 * l];
    for a in 0..3 {
        for b in 0..3 {
            for k in 0..l {
                without.rho[(a * 3 + b) * l + k] = s.rho[(a * p + b) * l + k];
            }
        }
    }
    let wo = without.shapley_exact(&y);
    for a in 0..3 {
        assert!((with.phi[a] - wo.phi[a]).abs() < 1e-12);
    }
}

#[test]
fn reputations_stay_a_distribution() {
    let mut g = Lcg(8);
    let mut w = vec![0.25; 4];
    for _ in 0..10_000 {
        let phi: Vec<f64> = (0..4).map(|_| 40.0 * (g.f() - 0.5)).collect();
        w = reputation_update(&w, &phi, 0.05);
        let s: f64 = w.iter().sum();
        assert!((s - 1.0).abs() < 1e-12);
        assert!(w.iter().all(|&x| x >= 0.0 && x.is_finite()));
    }
    // A huge credit must not overflow exp.
    let w = reputation_update(&[0.5, 0.5], &[1e6, 0.0], 1.0);
    assert_eq!(w, vec![1.0, 0.0]);
}

fn names() -> Vec<String> {
    vec!["a".into(), "b".into(), "c".into()]
}

#[test]
fn the_empty_bank_gives_no_signal() {
    let e = Engine::new(FusionConfig::paper(), Ontology::paper(), names()).unwrap();
    let (round, _) = e
        .parse(&record(
            vec![1.0, 2.0],
            &[("a", &["brake"]), ("b", &["stop", "brake"]), ("c", &[])],
            None,
        ))
        .unwrap();
    let inf = e.infer(&round);
    assert!(inf.signals.theta_pos.iter().all(|&t| t == 0.5));
    assert!(inf.signals.theta_neg.iter().all(|&t| t == 0.5));
    assert!(inf.signals.prior.iter().all(|&t| t == 0.5));
    assert!(inf.q.iter().all(|&q| q == 0.5), "{:?}", inf.q);
    let y = e.encode_truth(&["brake"]).unwrap();
    let out = e.credit(&inf.signals, &inf.w_used, &y, 0);
    assert!(out.phi.iter().all(|&p| p == 0.0));
    assert_eq!(out.w_after, out.w_before);
}

/// An engine state built from labelled rounds without credit (so every ablation shares it).
fn trained(ablations: Ablations) -> (Engine, Round) {
    let cfg = FusionConfig {
        k: 8,
        k_prior: 8,
        ablations,
        ..FusionConfig::paper()
    };
    let o = Ontology::paper();
    let mut e = Engine::new(cfg, o.clone(), names()).unwrap();
    let mut g = Lcg(3);
    let l = o.len();
    for t in 0..60u64 {
        let ctx: Vec<f64> = (0..5)
            .map(|_| g.f() - 0.5 + if t % 2 == 0 { 1.0 } else { 0.0 })
            .collect();
        let truth: Vec<u8> = (0..l).map(|_| (g.f() < 0.3) as u8).collect();
        let reports: Vec<u8> = (0..3 * l)
            .map(|i| truth[i % l] ^ (g.f() < 0.2 + 0.1 * (i / l) as f64) as u8)
            .collect();
        let round = Round {
            context: e.normalise_context(&ctx).unwrap(),
            present: vec![true, t % 7 != 0, true],
            reports,
        };
        e.apply(
            &LabelledRound {
                seq: t,
                round,
                truth,
                q: vec![0.3; l],
            },
            None,
        )
        .unwrap();
    }
    let (query, _) = e
        .parse(&record(
            vec![1.2, 0.9, 1.1, 0.7, 1.0],
            &[
                ("a", &["brake", "stop"]),
                ("b", &["brake"]),
                ("c", &["stop"]),
            ],
            None,
        ))
        .unwrap();
    (e, query)
}

#[test]
fn each_ablation_switches_off_exactly_its_part() {
    let (full, q) = trained(Ablations::default());
    let base = full.infer(&q).signals;
    assert!(
        base.rho.iter().any(|&r| r > 0.0),
        "the state must have correlations"
    );
    let one = |name: &str| {
        let (e, q) = trained(Ablations::from_name(name).unwrap());
        (e.infer(&q).signals, e, q)
    };

    let (s, _, _) = one("no-guardrail");
    assert!(s.rho.iter().all(|&r| r == 0.0));
    assert_eq!(
        (&s.theta_pos, &s.theta_neg, &s.prior),
        (&base.theta_pos, &base.theta_neg, &base.prior)
    );

    let (s, e, _) = one("no-context");
    assert_eq!(s.rho, base.rho);
    assert_ne!(s.theta_pos, base.theta_pos);
    // kappa = 1 over the whole bank: theta+ for reporter a, label brake (k=2) is a global frequency.
    let (mut ry, mut y) = (0.0, 0.0);
    for pos in 0..e.bank().len() {
        if e.bank().present(pos, 0) && e.bank().truth(pos, 2) == 1 {
            y += 1.0;
            ry += e.bank().report(pos, 0, 2) as f64;
        }
    }
    assert!((s.theta_pos[2] - (1.0 + ry) / (2.0 + y)).abs() < 1e-15);

    let (s, e, _) = one("per-model-score");
    assert_eq!(s, base);
    let truth = e.encode_truth(&["brake"]).unwrap();
    let out = e.credit(&s, &[1.0 / 3.0; 3], &truth, 0);
    assert_eq!(out.credit.method, ShapleyMethod::PerModelScore);
    let lam = s.llr();
    let lp = s.prior_logit();
    for a in 0..3 {
        assert_eq!(out.phi[a], s.value(&lam, &lp, &truth, &|b| b == a));
    }
    let shap = full.credit(&base, &[1.0 / 3.0; 3], &truth, 0);
    assert_ne!(out.phi, shap.phi);

    let (s, e, _) = one("frozen-reputation");
    assert_eq!(s, base);
    let out = e.credit(&s, &[1.0 / 3.0; 3], &truth, 0);
    assert_eq!(out.w_after, vec![1.0 / 3.0; 3]);
    assert_eq!(out.phi, shap.phi, "credit is still computed and reported");
    assert_ne!(shap.w_after, shap.w_before);
}

#[test]
fn rejected_rounds_name_the_problem_and_change_nothing() {
    let cfg = FusionConfig {
        dim: Some(3),
        ..FusionConfig::paper()
    };
    let e = Engine::new(cfg, Ontology::paper(), names()).unwrap();
    let before = format!("{e:?}");
    let cases: Vec<(RoundRecord, &str)> = vec![
        (
            record(vec![1.0, 0.0], &[("a", &[])], None),
            "dimension_mismatch",
        ),
        (
            record(vec![1.0, f64::NAN, 0.0], &[("a", &[])], None),
            "non_finite",
        ),
        (
            record(vec![0.0, 0.0, 0.0], &[("a", &[])], None),
            "bad_context",
        ),
        (record(vec![], &[("a", &[])], None), "bad_context"),
        (
            record(vec![1.0, 0.0, 0.0], &[("zed", &[])], None),
            "unknown_reporter",
        ),
        (
            record(vec![1.0, 0.0, 0.0], &[("", &[])], None),
            "unknown_reporter",
        ),
        (
            record(vec![1.0, 0.0, 0.0], &[("a", &["fly"])], None),
            "unknown_label",
        ),
        (record(vec![1.0, 0.0, 0.0], &[], None), "empty_coalition"),
        (
            record(vec![1.0, 0.0, 0.0], &[("a", &[])], Some(&["teleport"])),
            "unknown_label",
        ),
    ];
    for (rec, kind) in cases {
        let err: FusionError = e.parse(&rec).unwrap_err();
        assert_eq!(err.kind(), kind, "{err}");
    }
    assert_eq!(before, format!("{e:?}"));
    // Huge but finite numbers are a direction like any other.
    let (r, _) = e
        .parse(&record(vec![1e300, 1e300, 0.0], &[("a", &[])], None))
        .unwrap();
    assert!((r.context[0] - 0.5f64.sqrt()).abs() < 1e-15);
}
