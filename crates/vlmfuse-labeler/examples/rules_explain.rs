//! Development tool: prints the sentences and rule mentions of a text read from stdin.
use std::io::Read;
use vlmfuse_labeler::{rules, text};

fn main() {
    let mut t = String::new();
    std::io::stdin().read_to_string(&mut t).unwrap();
    if std::env::args().any(|a| a == "--lines") {
        // One answer per paragraph (blank-line separated): labels only.
        for para in t.split("\n\n").filter(|p| !p.trim().is_empty()) {
            let s = text::sentences(para);
            let m = rules::mentions(&s);
            let on: Vec<&str> = rules::decide(&s, &m)
                .into_iter()
                .filter(|d| d.1)
                .map(|d| d.0)
                .collect();
            println!("{:?}\n   => {on:?}", para.trim());
        }
        return;
    }
    let s = text::sentences(&t);
    for (i, x) in s.iter().enumerate() {
        println!("[{i}] {}", x.norm);
    }
    let m = rules::mentions(&s);
    for x in &m {
        let sn = &s[x.sentence];
        let span: Vec<&str> = (x.a..x.b).map(|k| sn.w(k)).collect();
        println!(
            "  {:<26} {:?} [{}] {:?} neg={} out={} hedge={} other={} past={} asserted={} pos={}",
            x.label,
            x.kind,
            x.sentence,
            span.join(" "),
            x.negated,
            x.rules_out,
            x.hedged,
            x.other,
            x.past,
            x.asserted,
            x.positive()
        );
    }
    let on: Vec<&str> = rules::decide(&s, &m)
        .into_iter()
        .filter(|d| d.1)
        .map(|d| d.0)
        .collect();
    println!("=> {on:?}");
}
