//! Development tool: the rule matcher alone on the TRAIN split, with its errors, so that rules
//! are designed without looking at the test split.
//!
//! ```text
//! cargo run -p vlmfuse-labeler --example rules_train -- [--errors] [--label ID] [--data FILE]
//! ```

use vlmfuse_labeler::{rules, text, Ontology};
use vlmfuse_testkit_models::labeler_eval::{
    default_dataset_path, f1_scores, load_dataset, to_mask,
};

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let errors = args.iter().any(|a| a == "--errors");
    let only = args
        .iter()
        .position(|a| a == "--label")
        .and_then(|i| args.get(i + 1).cloned());
    let onto = Ontology::default_driving();
    let data_path = args
        .iter()
        .position(|a| a == "--data")
        .and_then(|i| args.get(i + 1))
        .map_or_else(default_dataset_path, Into::into);
    let data = load_dataset(&data_path).unwrap();
    let hand = args.iter().any(|a| a == "--hand");
    let train: Vec<_> = data
        .iter()
        .filter(|e| e.split == "train" && (!hand || e.id.starts_with("h-")))
        .collect();
    let mut truth = Vec::new();
    let mut pred = Vec::new();
    for e in &train {
        let s = text::sentences(&e.text);
        let m = rules::mentions(&s);
        let d = rules::decide(&s, &m);
        let on: Vec<String> = d.iter().filter(|x| x.1).map(|x| x.0.to_string()).collect();
        let t = to_mask(&onto, &e.labels).unwrap();
        let p = to_mask(&onto, &on).unwrap();
        if errors && t != p {
            let name = |m: &Vec<bool>, o: &Vec<bool>| -> Vec<&str> {
                onto.labels()
                    .iter()
                    .enumerate()
                    .filter(|(k, _)| m[*k] && !o[*k])
                    .map(|(_, l)| l.id.as_str())
                    .collect()
            };
            let missed = name(&t, &p);
            let extra = name(&p, &t);
            if only
                .as_ref()
                .is_none_or(|l| missed.contains(&l.as_str()) || extra.contains(&l.as_str()))
            {
                println!(
                    "--- {}: missed {missed:?} extra {extra:?}\n{}",
                    e.id, e.text
                );
                for x in &m {
                    let sn = &s[x.sentence];
                    let span: Vec<&str> = (x.a..x.b).map(|k| sn.w(k)).collect();
                    if only.as_ref().is_none_or(|l| l == x.label) {
                        println!(
                            "    {:<26} {:?} {:?} neg={} hedge={} other={} past={} asserted={} | {}",
                            x.label, x.kind, span.join(" "), x.negated, x.hedged, x.other, x.past, x.asserted, sn.norm
                        );
                    }
                }
            }
        }
        truth.push(t);
        pred.push(p);
    }
    for prefix in ["a-", "h-"] {
        let idx: Vec<usize> = (0..train.len())
            .filter(|&i| train[i].id.starts_with(prefix))
            .collect();
        let t: Vec<Vec<bool>> = idx.iter().map(|&i| truth[i].clone()).collect();
        let p: Vec<Vec<bool>> = idx.iter().map(|&i| pred[i].clone()).collect();
        let f = f1_scores(&t, &p);
        println!(
            "train {prefix}* ({}): micro {:.3} macro {:.3}",
            idx.len(),
            f.micro,
            f.macro_
        );
    }
    let f = f1_scores(&truth, &pred);
    println!(
        "train ({}): micro {:.3} macro {:.3}",
        train.len(),
        f.micro,
        f.macro_
    );
    for (k, l) in onto.labels().iter().enumerate() {
        let col = |m: &[Vec<bool>]| m.iter().map(|r| vec![r[k]]).collect::<Vec<_>>();
        let (tp, fp, fnn) = truth
            .iter()
            .zip(&pred)
            .fold((0, 0, 0), |(a, b, c), (t, p)| {
                (
                    a + (t[k] && p[k]) as usize,
                    b + (!t[k] && p[k]) as usize,
                    c + (t[k] && !p[k]) as usize,
                )
            });
        println!(
            "  {:<28} F1 {:.3}  tp {tp:>3} fp {fp:>3} fn {fnn:>3}",
            l.id,
            f1_scores(&col(&truth), &col(&pred)).micro
        );
    }
}
