//! Clause splitting and negation cues.
//!
//! Sentence embeddings place "no need to brake" right next to "brake", so negation is decided
//! lexically per clause. Splitting into clauses first keeps a cue's scope small: in "there is no
//! traffic light, but stop at the junction" the "no" must not suppress "stop".

/// Words and contractions that negate what follows them in the same clause.
const CUES: &[&str] = &[
    "no",
    "not",
    "never",
    "without",
    "none",
    "nobody",
    "nothing",
    "neither",
    "nor",
    "cannot",
    "avoid",
    "unnecessary",
    "absent",
    "absence",
];

/// Phrases in which a cue does not negate the advice ("don't forget to check the blind spot").
const DOUBLE_NEGATIVES: &[&str] = &[
    "not forget",
    "never forget",
    "n't forget",
    "not neglect",
    "n't neglect",
    "never skip",
    "not skip",
    "n't skip",
    "no matter",
    "not only",
    "without fail",
];

/// Conjunctions that start a new clause (padded with spaces to match whole words).
const SPLIT_WORDS: &[&str] = &[
    " and ",
    " but ",
    " so ",
    " then ",
    " because ",
    " since ",
    " while ",
    " although ",
    " though ",
    " whereas ",
    " or ",
    " to avoid ",
    " in order to ",
    " given that ",
];

/// Splits a VLM answer into short clauses: sentences, then commas/semicolons/colons, then
/// clause-joining conjunctions. List markers and markdown are dropped.
pub fn split_clauses(text: &str) -> Vec<String> {
    let cleaned: String = text
        .chars()
        .map(|c| match c {
            '*' | '#' | '`' | '_' | '"' | '(' | ')' | '[' | ']' => ' ',
            c => c,
        })
        .collect();
    let mut out = Vec::new();
    for piece in cleaned.split(['.', ';', ':', '!', '?', '\n', ',']) {
        let mut rest = format!(" {} ", piece.trim().to_lowercase());
        let mut parts = Vec::new();
        while let Some((pos, len)) = SPLIT_WORDS
            .iter()
            .filter_map(|w| rest.find(w).map(|p| (p, w.len())))
            .min_by_key(|(p, _)| *p)
        {
            parts.push(rest[..pos].to_string());
            // Keep a leading space so that a conjunction right at the start still matches.
            rest = format!(" {}", &rest[pos + len..]);
        }
        parts.push(rest);
        for p in parts {
            let p = p
                .trim()
                .trim_start_matches(|c: char| c.is_ascii_digit() || c == '-' || c == ')')
                .trim();
            // Drop list markers and headings made of one word ("1", "rationale").
            if p.split_whitespace().count() >= 2 {
                out.push(p.to_string());
            }
        }
    }
    out
}

/// True when the clause contains a negation cue outside a double negative.
pub fn is_negated(clause: &str) -> bool {
    let mut c = format!(" {} ", clause.to_lowercase().replace('\u{2019}', "'"));
    for d in DOUBLE_NEGATIVES {
        c = c.replace(d, " ");
    }
    if c.contains("n't") {
        return true;
    }
    c.split(|ch: char| !ch.is_alphanumeric() && ch != '\'')
        .any(|w| CUES.contains(&w))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn splits_on_punctuation_and_conjunctions() {
        let c = split_clauses(
            "1. Scene: There is no traffic light, but a junction is ahead.\n2. Slow down and stop.",
        );
        assert_eq!(
            c,
            vec![
                "scene",
                "there is no traffic light",
                "a junction is ahead",
                "slow down",
                "stop"
            ]
            .into_iter()
            .filter(|s| s.split_whitespace().count() >= 2)
            .collect::<Vec<_>>()
        );
    }

    #[test]
    fn negation_cues() {
        assert!(is_negated("there is no traffic light"));
        assert!(is_negated("no need to brake"));
        assert!(is_negated("you don't have to stop"));
        assert!(is_negated("nobody is crossing the road"));
        assert!(!is_negated("don't forget to check the blind spot"));
        assert!(!is_negated("slow down for the crossing"));
        assert!(!is_negated("note the signal ahead"));
    }
}
