//! Vectors computed by hand from docs/PAPER-METHOD.md §2–4 (the arithmetic is in the comments).

// Indices mirror the formulas of docs/PAPER-METHOD.md on purpose: a naive transcription is the point.
#![allow(clippy::needless_range_loop, clippy::type_complexity)]

mod common;

use common::record;
use vlmfuse_fusion::{Engine, FusionConfig, LabelledRound, Ontology, RoundRecord};

fn rec(ctx: Vec<f64>, reports: &[(&str, &[&str])]) -> RoundRecord {
    record(ctx, reports, None)
}

fn learn(e: &mut Engine, seq: u64, ctx: Vec<f64>, reports: &[(&str, &[&str])], truth: &[&str]) {
    let (round, _) = e.parse(&rec(ctx, reports)).unwrap();
    let inf = e.infer(&round);
    let y = e.encode_truth(truth).unwrap();
    let out = e.credit(&inf.signals, &inf.w_used, &y, seq);
    e.apply(
        &LabelledRound {
            seq,
            round,
            truth: y,
            q: inf.q,
        },
        Some(&out),
    )
    .unwrap();
}

const BRAKE: usize = 2;
const STOP: usize = 4;

#[test]
fn one_reporter_one_neighbour() {
    let mut e = Engine::new(FusionConfig::paper(), Ontology::paper(), vec!["a".into()]).unwrap();
    // Bank: a reported {brake}, truth {brake}.
    learn(&mut e, 0, vec![3.0, 4.0], &[("a", &["brake"])], &["brake"]);
    // Query at the same direction: cos = 1, kappa = 1.
    let (round, _) = e.parse(&rec(vec![0.6, 0.8], &[("a", &["brake"])])).unwrap();
    let inf = e.infer(&round);
    let s = &inf.signals;
    // brake: a+ = 1+1, b+ = 1, a- = 1, b- = 1 -> theta+ = 2/3, theta- = 1/2; pi = (1+1)/(2+1) = 2/3.
    assert!((s.theta_pos[BRAKE] - 2.0 / 3.0).abs() < 1e-15);
    assert_eq!(s.theta_neg[BRAKE], 0.5);
    assert!((s.prior[BRAKE] - 2.0 / 3.0).abs() < 1e-15);
    // lambda = ln(4/3), w = 1: q = sigmoid(ln 2 + ln 4/3) = (8/3)/(11/3) = 8/11.
    assert!(
        (inf.q[BRAKE] - 8.0 / 11.0).abs() < 1e-12,
        "{}",
        inf.q[BRAKE]
    );
    // stop (r = 0, y = 0): theta+ = 1/2, theta- = 1/3, lambda = ln(0.5 / (2/3)) = ln(3/4);
    // pi = 1/3: q = sigmoid(ln(1/2) + ln(3/4)) = (3/8)/(11/8) = 3/11.
    assert!((inf.q[STOP] - 3.0 / 11.0).abs() < 1e-12);
    // Below 20 labelled rounds the threshold is 0.5: brake on, stop off.
    assert_eq!(inf.thresholds[BRAKE], 0.5);
    assert_eq!(inf.pred[BRAKE], 1);
    assert_eq!(inf.pred[STOP], 0);
}

#[test]
fn kernel_is_cosine_to_the_fourth_and_negative_cosines_count_zero() {
    let mut e = Engine::new(FusionConfig::paper(), Ontology::paper(), vec!["a".into()]).unwrap();
    learn(&mut e, 0, vec![1.0, 0.0], &[("a", &["brake"])], &["brake"]);
    learn(&mut e, 1, vec![-1.0, 0.0], &[("a", &[])], &["brake"]);
    // Query at 60 degrees from the first: cos = 0.5, kappa = 1/16; the second has cos = -0.5.
    let (round, _) = e
        .parse(&rec(vec![0.5, 3f64.sqrt() / 2.0], &[("a", &["brake"])]))
        .unwrap();
    let s = e.infer(&round).signals;
    // brake: a+ = 1 + 1/16, b+ = 1 + 0 -> theta+ = (17/16)/(33/16) = 17/33.
    assert!(
        (s.theta_pos[BRAKE] - 17.0 / 33.0).abs() < 1e-12,
        "{}",
        s.theta_pos[BRAKE]
    );
    // pi = (1 + 1/16) / (2 + 1/16) = 17/33 as well.
    assert!((s.prior[BRAKE] - 17.0 / 33.0).abs() < 1e-12);
}

#[test]
fn guardrail_divides_agreeing_llrs_by_one_plus_rho() {
    let names = vec!["a".to_string(), "b".to_string()];
    let mut e = Engine::new(FusionConfig::paper(), Ontology::paper(), names).unwrap();
    // Both wrongly report brake: errors (1,1) on brake, (0,0) elsewhere.
    learn(
        &mut e,
        0,
        vec![1.0, 0.0],
        &[("a", &["brake"]), ("b", &["brake"])],
        &[],
    );
    // rho(brake) from cells 11=1.5, 00=10=01=0.5: (0.75 - 0.25)/sqrt(2*1*2*1) = 0.25.
    // rho(stop): both right, cells 00 = 1.5, others 0.5: (0.5*1.5 - 0.5*0.5)/2 = 0.25 as well:
    // the phi coefficient is symmetric in flipping both errors, so agreeing while right counts
    // as correlation too (the paper method's formula as written).
    let (round, _) = e
        .parse(&rec(
            vec![1.0, 0.0],
            &[("a", &["brake"]), ("b", &["brake"])],
        ))
        .unwrap();
    let inf = e.infer(&round);
    let s = &inf.signals;
    let l = 14;
    assert!((s.rho[l + BRAKE] - 0.25).abs() < 1e-15, "rho(a,b,brake)");
    assert!((s.rho[l + STOP] - 0.25).abs() < 1e-15);
    // brake: theta+ = 1/2 (no positives), theta- = a-/(a-+b-) = 2/3 -> lambda = ln(4/3)^-1 = ln(3/4).
    // Each weighted by 1/2 and divided by 1.25 (they agree); two of them:
    // z = logit(pi) + 2 * 0.5 * ln(3/4) / 1.25, pi = 1/3.
    let z = (0.5f64).ln() + (0.75f64).ln() / 1.25;
    let q = 1.0 / (1.0 + (-z).exp());
    assert!((inf.q[BRAKE] - q).abs() < 1e-12, "{} vs {q}", inf.q[BRAKE]);
    let ex = e.explain(&inf);
    assert!((ex[BRAKE].contributions[0].1 - 0.5 * (0.75f64).ln() / 1.25).abs() < 1e-12);
}

#[test]
fn two_player_shapley_by_hand() {
    let names = vec!["a".to_string(), "b".to_string()];
    let mut e = Engine::new(FusionConfig::paper(), Ontology::paper(), names).unwrap();
    learn(
        &mut e,
        0,
        vec![1.0, 0.0],
        &[("a", &["brake"]), ("b", &[])],
        &["brake"],
    );
    let (round, _) = e
        .parse(&rec(vec![1.0, 0.0], &[("a", &["brake"]), ("b", &["stop"])]))
        .unwrap();
    let inf = e.infer(&round);
    let y = e.encode_truth(&["brake"]).unwrap();
    let s = &inf.signals;
    let (lam, lp) = (s.llr(), s.prior_logit());
    let v = |m: u8| s.value(&lam, &lp, &y, &|a| m >> a & 1 == 1);
    // phi_a = 1/2 (v{a} - 0) + 1/2 (v{a,b} - v{b}).
    let phi_a = 0.5 * v(1) + 0.5 * (v(3) - v(2));
    let phi_b = 0.5 * v(2) + 0.5 * (v(3) - v(1));
    let out = e.credit(&inf.signals, &inf.w_used, &y, 1);
    assert!((out.phi[0] - phi_a).abs() < 1e-15);
    assert!((out.phi[1] - phi_b).abs() < 1e-15);
    // w <- w exp(eta phi) / sum.
    let (ea, eb) = ((0.01 * phi_a).exp(), (0.01 * phi_b).exp());
    assert!((out.w_after[0] - ea / (ea + eb)).abs() < 1e-15);
    assert!(phi_a > 0.0, "a was right about brake and must gain");
}
