// scratch diagnostics (not committed): diag FILE N SEED [toml]
use vlmfuse_fusion::curve::hide_labels;
use vlmfuse_fusion::replay::{history_len, prepare};
use vlmfuse_fusion::*;
fn main() {
    let a: Vec<String> = std::env::args().collect();
    let text = std::fs::read_to_string(&a[1]).unwrap();
    let recs: Vec<(usize, RoundRecord)> = text
        .lines()
        .enumerate()
        .map(|(i, l)| (i + 1, serde_json::from_str(l).unwrap()))
        .collect();
    let mut cfg = FusionConfig::default();
    if a.len() > 4 {
        #[derive(serde::Deserialize)]
        struct F {
            fusion: FusionConfig,
        }
        cfg = toml::from_str::<F>(&std::fs::read_to_string(&a[4]).unwrap())
            .unwrap()
            .fusion;
    }
    cfg.method = Method::Adaptive;
    let keep: Option<usize> = a[2].parse().ok();
    let (mut e, rounds) = prepare(&cfg, &Ontology::paper(), &recs).unwrap();
    let nh = history_len(rounds.len(), 0.7);
    let (rounds, _) = hide_labels(&rounds, nh, keep, a[3].parse().unwrap());
    for (t, pr) in rounds.iter().enumerate().take(nh) {
        let inf = e.infer(&pr.round);
        e.observe(t as u64, &pr.round, &inf).unwrap();
        if let Some(y) = &pr.truth {
            let o = e.credit(&inf.signals, &inf.w_used, y, t as u64);
            e.apply(
                &LabelledRound {
                    seq: t as u64,
                    round: pr.round.clone(),
                    truth: y.clone(),
                    q: inf.q.clone(),
                },
                Some(&o),
            )
            .unwrap();
        }
    }
    let ad = e.adaptive().unwrap();
    println!(
        "labelled {} w {:?} thr {:?}",
        e.labelled(),
        e.reputations(),
        e.threshold().thresholds()[0]
    );
    println!("calib pooled {:?}", ad.calibrator().pooled());
    for k in 0..14 {
        print!(
            "k{k} cal {:.2?} pi {:.3} |",
            ad.calibrator().params(k),
            e.global_pi(k)
        );
        for i in 0..3 {
            let (p, q) = e.global_theta(i, k);
            print!(" {:.2}/{:.2}", p, q);
        }
        println!();
    }
    // truth-based stats
    let l = 14;
    let mut st = vec![[0f64; 4]; 3 * l];
    let mut pos = vec![0f64; l];
    let mut cnt = 0.0;
    for pr in rounds.iter().take(nh) {
        if let Some(_) = &pr.truth {}
    }
    let (_, full) = prepare(&cfg, &Ontology::paper(), &recs).unwrap();
    for pr in full.iter().take(nh) {
        let y = pr.truth.as_ref().unwrap();
        cnt += 1.0;
        for k in 0..l {
            pos[k] += y[k] as f64;
            for i in 0..3 {
                if pr.round.present[i] {
                    let r = pr.round.reports[i * l + k];
                    let c = &mut st[i * l + k];
                    match (r, y[k]) {
                        (1, 1) => c[0] += 1.,
                        (0, 1) => c[1] += 1.,
                        (1, 0) => c[2] += 1.,
                        _ => c[3] += 1.,
                    }
                }
            }
        }
    }
    for k in 0..14 {
        print!("k{k} TRUE pi {:.3} |", pos[k] / cnt);
        for i in 0..3 {
            let c = st[i * l + k];
            print!(" {:.2}/{:.2}", c[0] / (c[0] + c[1]), c[2] / (c[2] + c[3]));
        }
        println!();
    }
}
