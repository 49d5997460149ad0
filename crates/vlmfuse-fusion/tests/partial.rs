//! Partial feedback in the engine (truth `UNKNOWN` for the labels a feedback does not give):
//! credit is computed on the known labels only, a round labelled in parts teaches what one full
//! label teaches, and a partly labelled pool entry keeps estimating only its unknown labels.

mod common;

use common::Lcg;
use vlmfuse_fusion::{
    Ablations, Engine, FusionConfig, LabelledRound, Method, Ontology, Round, UNKNOWN,
};

fn names() -> Vec<String> {
    vec!["a".into(), "b".into(), "c".into()]
}

/// Context, presence, reports and truth of one round.
type Sample = (Vec<f64>, Vec<bool>, Vec<u8>, Vec<u8>);

/// Random labelled rounds in two context clusters, reporters of different reliability.
fn rounds(n: u64, l: usize, seed: u64) -> Vec<Sample> {
    let mut g = Lcg(seed);
    (0..n)
        .map(|t| {
            let ctx: Vec<f64> = (0..5)
                .map(|_| g.f() - 0.5 + if t % 2 == 0 { 1.0 } else { 0.0 })
                .collect();
            let truth: Vec<u8> = (0..l).map(|_| (g.f() < 0.3) as u8).collect();
            let reports: Vec<u8> = (0..3 * l)
                .map(|i| truth[i % l] ^ (g.f() < 0.1 + 0.15 * (i / l) as f64) as u8)
                .collect();
            (ctx, vec![true, t % 5 != 0, true], reports, truth)
        })
        .collect()
}

fn round(e: &Engine, ctx: &[f64], present: &[bool], reports: &[u8]) -> Round {
    Round {
        context: e.normalise_context(ctx).unwrap(),
        present: present.to_vec(),
        reports: reports.to_vec(),
    }
}

/// Feeds every round as the service does (infer, observe, credit, apply), each truth split by
/// `split` into the feedbacks it arrives in.
fn run(cfg: &FusionConfig, split: &dyn Fn(&[u8]) -> Vec<Vec<u8>>) -> Engine {
    let o = Ontology::paper();
    let l = o.len();
    let mut e = Engine::new(cfg.clone(), o, names()).unwrap();
    for (t, (ctx, present, reports, truth)) in rounds(80, l, 5).into_iter().enumerate() {
        let r = round(&e, &ctx, &present, &reports);
        let inf = e.infer(&r);
        e.observe(t as u64, &r, &inf).unwrap();
        for part in split(&truth) {
            let o = e.credit(&inf.signals, &inf.w_used, &part, t as u64);
            let lr = LabelledRound {
                seq: t as u64,
                round: r.clone(),
                truth: part,
                q: inf.q.clone(),
            };
            e.apply(&lr, Some(&o)).unwrap();
        }
    }
    e
}

fn whole(y: &[u8]) -> Vec<Vec<u8>> {
    vec![y.to_vec()]
}

/// The first half of the labels, then the rest.
fn halves(y: &[u8]) -> Vec<Vec<u8>> {
    let h = y.len() / 2;
    let a = (0..y.len())
        .map(|k| if k < h { y[k] } else { UNKNOWN })
        .collect();
    let b = (0..y.len())
        .map(|k| if k >= h { y[k] } else { UNKNOWN })
        .collect();
    vec![a, b]
}

#[test]
fn credit_ignores_the_labels_a_feedback_does_not_give() {
    let cfg = FusionConfig::paper();
    let e = run(&cfg, &whole);
    let l = e.ontology().len();
    let mut g = Lcg(11);
    for _ in 0..20 {
        let (ctx, present, reports, _) = &rounds(1, l, (g.f() * 1e9) as u64)[0];
        let r = round(&e, ctx, present, reports);
        let inf = e.infer(&r);
        // Two truths that agree on the known labels 0..4 and differ elsewhere.
        let y1: Vec<u8> = (0..l).map(|_| (g.f() < 0.5) as u8).collect();
        let mut y2 = y1.clone();
        for v in &mut y2[4..] {
            *v ^= 1;
        }
        let part =
            |y: &[u8]| -> Vec<u8> { (0..l).map(|k| if k < 4 { y[k] } else { UNKNOWN }).collect() };
        let full1 = e.credit(&inf.signals, &inf.w_used, &y1, 1);
        let full2 = e.credit(&inf.signals, &inf.w_used, &y2, 1);
        assert_ne!(
            full1.phi, full2.phi,
            "the unknown labels must matter when known"
        );
        let p1 = e.credit(&inf.signals, &inf.w_used, &part(&y1), 1);
        let p2 = e.credit(&inf.signals, &inf.w_used, &part(&y2), 1);
        assert_eq!(p1, p2);
        // Efficiency on the known labels.
        let sum: f64 = p1.credit.phi.iter().sum();
        assert!((sum - p1.credit.v_full).abs() < 1e-9);
        // Nothing known: no credit at all.
        let none = e.credit(&inf.signals, &inf.w_used, &vec![UNKNOWN; l], 1);
        assert!(none.credit.phi.iter().all(|&p| p.abs() < 1e-12), "{none:?}");
    }
}

#[test]
fn paper_labels_in_two_parts_teach_what_one_full_label_does() {
    // Reputations frozen and no guardrail: what is left of the posterior is the bank (its
    // reliabilities and prior), which must end up identical however the labels arrived.
    let cfg = FusionConfig {
        k: 10,
        k_prior: 10,
        ablations: Ablations {
            frozen_reputation: true,
            no_guardrail: true,
            ..Ablations::default()
        },
        ..FusionConfig::paper()
    };
    let a = run(&cfg, &whole);
    let b = run(&cfg, &halves);
    assert_eq!(b.labelled(), 2 * a.labelled());
    assert_eq!(a.bank().len(), b.bank().len());
    let l = a.ontology().len();
    for (ctx, present, reports, _) in rounds(10, l, 99) {
        let qa = a.infer(&round(&a, &ctx, &present, &reports)).q;
        let qb = b.infer(&round(&b, &ctx, &present, &reports)).q;
        assert_eq!(qa, qb);
    }
    // A bank entry with only half its labels known really is partial: the other half's
    // statistics differ from the full bank's until the second part comes.
    let c = run(&cfg, &|y: &[u8]| vec![halves(y).remove(0)]);
    let (ctx, present, reports, _) = &rounds(1, l, 7)[0];
    let qa = a.infer(&round(&a, ctx, present, reports)).q;
    let qc = c.infer(&round(&c, ctx, present, reports)).q;
    assert_eq!(qa[..l / 2], qc[..l / 2]);
    assert_ne!(qa[l / 2..], qc[l / 2..]);
    assert!(qc[l / 2..].iter().all(|&q| (q - 0.5).abs() < 0.5));
}

#[test]
fn adaptive_partial_entries_become_labelled_when_complete() {
    let cfg = FusionConfig {
        method: Method::Adaptive,
        ..FusionConfig::default()
    };
    // Only the first half ever known: every entry stays partial (with the unlabelled for EM).
    let half = run(&cfg, &|y: &[u8]| vec![halves(y).remove(0)]);
    assert_eq!(half.pool_sizes(), Some((0, 80)));
    // Both halves: every entry ends labelled, as with full feedback.
    let both = run(&cfg, &halves);
    assert_eq!(both.pool_sizes(), Some((80, 0)));
    let full = run(&cfg, &whole);
    assert_eq!(full.pool_sizes(), Some((80, 0)));
    // The known half teaches: its posteriors are closer to the fully labelled engine's than
    // an engine that never got a label.
    let none = run(&cfg, &|_: &[u8]| Vec::new());
    let l = full.ontology().len();
    let mut d_half = 0.0;
    let mut d_none = 0.0;
    for (ctx, present, reports, _) in rounds(20, l, 31) {
        let qf = full.infer(&round(&full, &ctx, &present, &reports)).q;
        let qh = half.infer(&round(&half, &ctx, &present, &reports)).q;
        let qn = none.infer(&round(&none, &ctx, &present, &reports)).q;
        for k in 0..l / 2 {
            d_half += (qf[k] - qh[k]).abs();
            d_none += (qf[k] - qn[k]).abs();
        }
    }
    assert!(d_half < d_none, "{d_half} vs {d_none}");
}
