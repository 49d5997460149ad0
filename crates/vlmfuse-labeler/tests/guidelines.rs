//! Every example of `tests/data/labeler/GUIDELINES.md` is read as the guidelines say: the "+"
//! and "−" examples of each label's section (that label on or off), and the worked hard cases
//! (the exact label set). Rules only, no model: this runs everywhere.

use std::path::Path;
use vlmfuse_labeler::{rules, text, Ontology};

fn labels(t: &str) -> Vec<String> {
    let s = text::sentences(t);
    let m = rules::mentions(&s);
    rules::decide(&s, &m)
        .into_iter()
        .filter(|d| d.1)
        .map(|d| d.0.to_string())
        .collect()
}

fn quoted(line: &str) -> Vec<String> {
    // Each "..." of a bullet is one example ("The light ahead is red." / "Lights on red.").
    let mut out = Vec::new();
    let mut rest = line;
    while let Some(a) = rest.find('"') {
        let Some(b) = rest[a + 1..].find('"') else {
            break;
        };
        out.push(rest[a + 1..a + 1 + b].to_string());
        rest = &rest[a + 1 + b + 1..];
    }
    out
}

#[test]
fn guideline_examples() {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../tests/data/labeler/GUIDELINES.md");
    let g = std::fs::read_to_string(path).unwrap();
    let onto = Ontology::default_driving();
    let mut section: Option<String> = None;
    let mut bad = Vec::new();
    let mut n = 0;
    for line in g.lines() {
        if let Some(h) = line.strip_prefix("### ") {
            section = onto.index_of(h.trim()).map(|_| h.trim().to_string());
            continue;
        }
        if line.starts_with("## ") {
            section = None;
        }
        let Some(label) = &section else { continue };
        let (want, body) = if let Some(b) = line.strip_prefix("- \\+ ") {
            (true, b)
        } else if let Some(b) = line.strip_prefix("- − ") {
            (false, b)
        } else {
            continue;
        };
        // Only the quotes before the parenthetical note are examples.
        let body = body.split(" (").next().unwrap_or(body);
        for ex in quoted(body) {
            n += 1;
            let got = labels(&ex);
            if got.contains(label) != want {
                bad.push(format!(
                    "[{label} {}] {ex:?} -> {got:?}",
                    if want { "+" } else { "-" }
                ));
            }
        }
    }
    // Part 3: the worked hard cases, whole label sets.
    let mut in_table = false;
    for line in g.lines() {
        if line.starts_with("| answer | labels |") {
            in_table = true;
            continue;
        }
        if in_table {
            if !line.starts_with('|') {
                in_table = false;
                continue;
            }
            let cols: Vec<&str> = line.split('|').map(str::trim).collect();
            if cols.len() < 3 || cols[1].starts_with("---") {
                continue;
            }
            let ex = cols[1].trim_matches('"').trim_end_matches('…');
            let mut want: Vec<String> = cols[2]
                .split(',')
                .map(|s| s.trim().to_string())
                .filter(|s| !s.is_empty() && s != "—")
                .collect();
            want.sort_by_key(|id| onto.index_of(id));
            n += 1;
            let got = labels(ex);
            if got != want {
                bad.push(format!("[worked] {ex:?} -> {got:?}, want {want:?}"));
            }
        }
    }
    assert!(n > 120, "parsed only {n} examples");
    assert!(
        bad.is_empty(),
        "{} of {n} examples:\n{}",
        bad.len(),
        bad.join("\n")
    );
}

/// Reading and the rules never panic, whatever the text: `/v1/label` takes arbitrary strings.
/// Random mixes of driving words, contractions, punctuation, list markers, JSON, and non-ASCII
/// (combining marks, wide characters, emoji, right-to-left, a lone surrogate-free odd byte
/// sequence), with the items and polarity the embedding matcher computes on top.
#[test]
fn reading_never_panics_on_arbitrary_text() {
    let pieces = [
        "brake",
        "don't",
        "won't",
        "n't",
        "no",
        "not",
        "stop",
        "turn",
        "left",
        "right",
        "exit",
        "3rd",
        "be",
        "ready",
        "to",
        "if",
        "may",
        "slow",
        "down",
        "ease",
        "off",
        "zebra",
        "red",
        "light",
        "weather",
        "isn't",
        "a",
        "factor",
        "yield",
        "give",
        "way",
        "keep",
        "merge",
        "1.",
        "2)",
        "-",
        "*",
        "•",
        "**",
        ":",
        ";",
        ",",
        ".",
        "!",
        "?",
        "...",
        "(",
        ")",
        "\"",
        "'",
        "’",
        "—",
        "–",
        "\n",
        "\n\n",
        "\t",
        "  ",
        "{",
        "}",
        "[",
        "]",
        "\"brake\": false",
        "é",
        "e\u{301}",
        "ß",
        "İ",
        "ﬁ",
        "日本",
        "😀",
        "👍🏽",
        "\u{200d}",
        "\u{202e}",
        "مرحبا",
        "\u{0}",
        "\u{feff}",
        "Ⅻ",
        "１２３",
        "%",
        "&",
        "#",
        "http://x.y/z",
        "e.g.",
        "i.e.",
    ];
    let mut rng = vlmfuse_testkit::rng::SplitMix64::new(11);
    for _ in 0..3000 {
        let n = (rng.next_u64() % 40) as usize;
        let mut t = String::new();
        for _ in 0..n {
            t.push_str(pieces[(rng.next_u64() % pieces.len() as u64) as usize]);
            if !rng.next_u64().is_multiple_of(3) {
                t.push(' ');
            }
        }
        let s = text::sentences(&t);
        let m = rules::mentions(&s);
        let _ = rules::decide(&s, &m);
        for x in &s {
            for (a, b) in rules::items(x) {
                let _ = rules::item_polarity(x, a, b);
                let _ = rules::advice_item(x, a, b);
            }
        }
    }
}
