// scratch diagnostics (not committed)
use vlmfuse_fusion::replay::{prepare, ParsedRound};
use vlmfuse_fusion::*;
fn main() {
    let a: Vec<String> = std::env::args().collect();
    let text = std::fs::read_to_string(&a[1]).unwrap();
    let recs: Vec<(usize, RoundRecord)> = text.lines().enumerate().map(|(i, l)| (i + 1, serde_json::from_str(l).unwrap())).collect();
    let mut cfg = FusionConfig::default();
    cfg.method = Method::Adaptive;
    if a.len() > 2 { cfg.adaptive.half_life = a[2].parse().unwrap(); }
    let (mut e, rounds): (Engine, Vec<ParsedRound>) = prepare(&cfg, &Ontology::paper(), &recs).unwrap();
    for (t, pr) in rounds.iter().enumerate() {
        let inf = e.infer(&pr.round);
        e.observe(t as u64, &pr.round, &inf).unwrap();
        if let Some(y) = &pr.truth {
            let o = e.credit(&inf.signals, &inf.w_used, y, t as u64);
            e.apply(&LabelledRound { seq: t as u64, round: pr.round.clone(), truth: y.clone(), q: inf.q.clone() }, Some(&o)).unwrap();
        }
        if t % 150 == 149 {
            let n = e.reporters().len();
            let mut line = format!("t={t} w={:?}", e.reputations().iter().map(|v| (v * 1000.0).round() / 1000.0).collect::<Vec<_>>());
            for i in 0..n {
                let (mut tp, mut tn) = (0.0, 0.0);
                for k in 0..14 { let (p, q) = e.global_theta(i, k); tp += p / 14.0; tn += q / 14.0; }
                line += &format!(" | {} tpr {:.2} fpr {:.2}", e.reporters()[i], tp, tn);
            }
            let s = &inf.signals;
            let th: Vec<String> = (0..s.coalition.len()).map(|m| format!("{:.2}/{:.2}", (0..14).map(|k| s.theta_pos[m*14+k]).sum::<f64>()/14.0, (0..14).map(|k| s.theta_neg[m*14+k]).sum::<f64>()/14.0)).collect();
            println!("{line} local {:?} w {:?}", th, s.w);
        }
    }
}
