//! Reading a VLM answer the way the annotation guidelines do (tests/data/labeler/GUIDELINES.md):
//! normalisation, sentences, clause parts, and the scope of negation, hedges and other agents.
//!
//! Why scopes and not whole-clause flags: the guidelines decide per phrase. "No need to stop,
//! just slow down" negates `stop` and keeps `brake`; "slow down, be ready to stop" hedges only
//! `stop`; "be ready to stop at the red light" hedges `stop` but still asserts the light; "the
//! car ahead is braking, so brake too" is another road user's action followed by ours. Each
//! mention is therefore located (word span) and judged by the cues around it.
//!
//! Everything here is pure string work, no model, so it is fast and deterministic.

use std::collections::HashSet;
use std::sync::OnceLock;

/// A word of a normalised sentence, with its byte span in [`Sentence::norm`].
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Word {
    pub text: String,
    pub start: usize,
    pub end: usize,
}

/// One sentence (or bullet, or `key: value` line) of an answer.
#[derive(Debug, Clone)]
pub struct Sentence {
    /// The sentence as written (trimmed), for evidence.
    pub original: String,
    /// Lower case, contractions expanded, typos corrected, punctuation as separate tokens,
    /// words joined by single spaces.
    pub norm: String,
    pub words: Vec<Word>,
    /// Ends with a question mark (a question is not a recommendation).
    pub question: bool,
}

impl Sentence {
    /// Index of the word containing byte `pos` of `norm` (the first word at or after it).
    pub fn word_at(&self, pos: usize) -> usize {
        self.words.partition_point(|w| w.end <= pos)
    }

    /// Word indices covering the byte range `[start, end)`.
    pub fn span(&self, start: usize, end: usize) -> (usize, usize) {
        let a = self.word_at(start);
        let b = self.words.partition_point(|w| w.start < end);
        (a, b.max(a + 1).min(self.words.len()))
    }

    pub fn w(&self, i: usize) -> &str {
        self.words.get(i).map_or("", |w| w.text.as_str())
    }
}

/// Contractions and spellings mapped to the forms the rules are written in.
const REWRITES: &[(&str, &str)] = &[
    ("can't", "can not"),
    ("cannot", "can not"),
    ("won't", "will not"),
    ("shan't", "shall not"),
    ("n't", " not"),
    ("let's", "let us"),
    ("i'm", "i am"),
    ("'re", " are"),
    ("'ll", " will"),
    ("'ve", " have"),
    ("'d", " would"),
    ("it's", "it is"),
    ("there's", "there is"),
    ("that's", "that is"),
    ("what's", "what is"),
    ("here's", "here is"),
    ("light's", "light is"),
    ("lights's", "lights is"),
    ("signal's", "signal is"),
    ("road's", "road is"),
    ("lane's", "lane is"),
    ("'s", ""),
    ("s'", "s"),
];

/// Connectives that end a negation's scope (the cue negates its own phrase only).
pub const NEG_BREAK: &[&str] = &[
    "but",
    "just",
    "instead",
    "so",
    "then",
    "and",
    "because",
    "since",
    "while",
    "although",
    "though",
    "whereas",
    "however",
    "yet",
    "until",
    "unless",
    "once",
    "when",
    "otherwise",
    "simply",
    "only",
    "rather",
    "as",
    "after",
    "before",
    "therefore",
    "thus",
    "which",
    "that",
    "if",
];

/// Punctuation tokens that end a clause part.
pub const PUNCT_BREAK: &[&str] = &[",", ";", ":", "(", ")", "-", "=", "?", "!"];

/// Connectives that end a hedge's scope (G2: a hedge does not spread past "but", "and then
/// definitely", or into a new main clause introduced by "so").
pub const HEDGE_BREAK: &[&str] = &[
    "but",
    "however",
    "although",
    "though",
    "whereas",
    "definitely",
    "certainly",
    "so",
    "therefore",
    "thus",
    "instead",
    "anyway",
    "regardless",
    "still",
];

/// Words of the domain that the typo corrector may correct towards. Everything the rules key
/// on, plus its inflections.
const LEXICON: &str = "ahead accelerate accelerating acceleration accelerator adjust adapt \
    adjacent amber approach approaching arrow avoid behind bend blind blindspot brake brakes \
    braking break brakes carriageway carefully carry caution change changing check checking \
    circle circulating clear close closely coming conditions continue continuing corner \
    crossing crossings crosswalk crossroads cruise cruising cyclist cyclists decelerate \
    distance drive driving drizzle drop dry ease exit fog foggy following freeway frost gap \
    give going gradually green hazard headlights highway hold ice icy increase indicate \
    intersection intersections junction junctions keep lane lanes left light lights maintain \
    manoeuvre maneuver maintain merge merging mirror mirrors mist motorway move normal \
    normally onto oncoming overtake pass pedestrian pedestrians pelican priority proceed \
    puffin pull rain raining reduce right road roundabout route safe safely shoulder signal \
    signals signalised signalized slip slippery slow slowing slowly sleet slush snow speed \
    spot stop stopping straight street stationary tailgate tailgating through toucan traffic \
    turn turning vehicle visibility wait waiting weather wet yellow yield yielding zebra \
    accelerate route going coming ahead behind slowdown snowing snowy raining rainy misty \
    frosty windy drizzling pouring spray slushy showers downpour hail storm stormy gusty \
    shower sunny cloudy overcast freezing flooded flooding puddle puddles";

/// Ordinary words that are one edit away from a lexicon word and must stay as written.
const KEEP: &[&str] = &[
    "sight", "night", "might", "tight", "eight", "fight", "bright", "slight", "flight", "lift",
    "loft", "list", "lost", "last", "less", "lest", "lean", "late", "line", "lines", "like",
    "lime", "live", "life", "lake", "load", "lead", "read", "ride", "rode", "role", "rule", "rate",
    "race", "rail", "rain", "gain", "main", "pain", "raid", "rein", "mist", "must", "most", "mast",
    "wind", "kind", "mind", "find", "bind", "wine", "wise", "wide", "stay", "stab", "step", "stem",
    "stun", "shop", "ship", "slot", "slit", "slim", "slip", "blow", "glow", "flow", "show", "snow",
    "stow", "grow", "brow", "know", "knew", "slew", "spit", "spin", "span", "spun", "spat",
    "spotted", "turf", "tune", "torn", "burn", "tern", "bake", "make", "take", "wake", "lake",
    "fake", "cake", "rake", "sake", "bike", "like", "field", "wield", "shield", "wait", "bait",
    "gait", "weight", "height", "fright", "freight", "brakes", "breaks", "broke", "brave", "grave",
    "crave", "drove", "prove", "stone", "store", "stare", "state", "stole", "scope", "slope",
    "close", "chose", "those", "these", "there", "where", "three", "here", "hear", "near", "rear",
    "gear", "year", "clean", "clear", "cleat", "drop", "crop", "prop", "shop", "stopped", "topped",
    "hopped", "spotted", "crossed", "cross", "gross", "press", "dress", "boss", "moss", "loss",
    "signs", "sign", "design", "assign", "mirrored", "error", "terror", "pass", "past", "paste",
    "pause", "place", "plane", "plan", "plain", "brain", "train", "drain", "grain", "strain",
    "trait", "lights", "rights", "nights", "fights", "flights", "turns", "runs", "rings", "roads",
    "loads", "toads", "goads", "lane", "land", "lend", "lens", "lent", "lift", "left", "gift",
    "rift", "shift", "drift", "swift", "thrift", "yields", "fields", "speedy", "spend", "spent",
    "spell", "spill", "still", "stall", "steal", "steel", "stool", "spool", "stock", "stuck",
    "stack", "track", "trick", "truck", "trunk", "drunk", "brake", "wheel", "while", "whole",
    "white", "write", "wrote", "route", "rout", "rough", "cough", "tough", "though", "through",
    "thought", "taught", "caught", "ought", "bought", "sought", "fought", "drought", "doubt",
    "about", "abut", "front", "driver", "drivers", "river", "rivers", "frosty", "lover", "liver",
    "lever", "cover", "rover", "mover", "seeing", "being", "doing", "gone", "done", "tone", "bone",
    "lone", "cones", "cone", "zone", "zones", "pole", "poles", "hole", "holes", "mile", "miles",
    "tile", "pile", "wine", "wind", "winds", "windy", "trail", "trailer", "trial", "rails",
    "sleek", "slick", "slice", "spice", "space", "spare", "spark", "speak", "spear", "steer",
    "sheer", "cheer", "stair", "stain", "stall", "start", "stark", "stars", "stare", "stove",
    "above", "glove", "grove", "drove", "droves", "shove", "shoved", "grader", "greener", "braid",
    "brain", "bread", "break", "breaking", "broken", "brakes", "breaks", "brave", "easy", "easier",
    "easily", "more", "mode", "slower", "lower", "power", "tower", "faster", "sower", "mower",
    "lover", "loser", "poser", "rider", "wider", "cider",
];

fn lexicon() -> &'static (HashSet<&'static str>, Vec<&'static str>) {
    static L: OnceLock<(HashSet<&'static str>, Vec<&'static str>)> = OnceLock::new();
    L.get_or_init(|| {
        let words: Vec<&str> = LEXICON.split_whitespace().collect();
        let mut known: HashSet<&str> = words.iter().copied().collect();
        known.extend(KEEP.iter().copied());
        (known, words)
    })
}

/// Optimal-string-alignment distance (Levenshtein with adjacent transpositions), capped.
fn osa(a: &[u8], b: &[u8], cap: usize) -> usize {
    if a.len().abs_diff(b.len()) > cap {
        return cap + 1;
    }
    let (n, m) = (a.len(), b.len());
    let mut d = vec![vec![0usize; m + 1]; n + 1];
    for (i, row) in d.iter_mut().enumerate() {
        row[0] = i;
    }
    for (j, v) in d[0].iter_mut().enumerate() {
        *v = j;
    }
    for i in 1..=n {
        for j in 1..=m {
            let cost = usize::from(a[i - 1] != b[j - 1]);
            let mut v = (d[i - 1][j] + 1)
                .min(d[i][j - 1] + 1)
                .min(d[i - 1][j - 1] + cost);
            if i > 1 && j > 1 && a[i - 1] == b[j - 2] && a[i - 2] == b[j - 1] {
                v = v.min(d[i - 2][j - 2] + 1);
            }
            d[i][j] = v;
        }
    }
    d[n][m]
}

/// Which words are real words, so that only misspellings get corrected. The built-in list
/// covers the domain; the embedding labeler adds its tokenizer's whole-word vocabulary (30k
/// English words), so that "driver" or "front" are never "corrected" to "drive" or "frost".
#[derive(Debug, Clone, Default)]
pub struct Speller {
    known: HashSet<String>,
}

impl Speller {
    /// A speller that also knows `words`.
    pub fn with_words<I: IntoIterator<Item = String>>(words: I) -> Self {
        Self {
            known: words.into_iter().collect(),
        }
    }

    pub fn correct(&self, word: &str) -> Option<&'static str> {
        if self.known.contains(word) {
            return None;
        }
        correct(word)
    }
}

/// Corrects a misspelt domain word (G10: "brak", "intersecton", "pedestrain", "yeild"): a word
/// of four letters or more that is not known, one edit from exactly one lexicon word (two
/// edits for words of eight letters or more), with the same first letter, and not that word
/// with a suffix ("driver", "slows").
pub fn correct(word: &str) -> Option<&'static str> {
    let (known, words) = lexicon();
    if word.len() < 4 || known.contains(word) || !word.bytes().all(|b| b.is_ascii_lowercase()) {
        return None;
    }
    let cap = if word.len() >= 8 { 2 } else { 1 };
    let mut best: Option<(&str, usize)> = None;
    let mut tie = false;
    for &w in words {
        if w.as_bytes()[0] != word.as_bytes()[0] || word.starts_with(w) && word.len() > w.len() {
            continue;
        }
        let d = osa(word.as_bytes(), w.as_bytes(), cap);
        if d > cap {
            continue;
        }
        match best {
            Some((_, bd)) if d > bd => {}
            Some((bw, bd)) if d == bd => tie |= bw != w,
            _ => {
                best = Some((w, d));
                tie = false;
            }
        }
    }
    match best {
        Some((w, _)) if !tie => Some(w),
        _ => None,
    }
}

/// Common misspellings that one edit does not reach or that are ambiguous by distance.
const TYPOS: &[(&str, &str)] = &[
    ("dwon", "down"),
    ("ahaed", "ahead"),
    ("ahed", "ahead"),
    ("ligth", "light"),
    ("ligths", "lights"),
    ("lite", "light"),
    ("giev", "give"),
    ("gve", "give"),
    ("goin", "going"),
    ("chek", "check"),
    ("blindspot", "blind spot"),
    ("abit", "a bit"),
    ("tailgait", "tailgate"),
    ("tailgaiting", "tailgating"),
    ("roundabuot", "roundabout"),
    ("comming", "coming"),
    ("theres", "there is"),
    ("dont", "do not"),
    ("doesnt", "does not"),
    ("didnt", "did not"),
    ("isnt", "is not"),
    ("arent", "are not"),
    ("cant", "can not"),
    ("wont", "will not"),
    ("shouldnt", "should not"),
    ("youre", "you are"),
    ("thats", "that is"),
    ("slowdown", "slow down"),
    ("stoplight", "stop light"),
    ("stoplights", "stop lights"),
    ("crosswalks", "crosswalk"),
    ("zebras", "zebra"),
    ("maneuver", "manoeuvre"),
    ("maneuvers", "manoeuvres"),
    ("signalized", "signalised"),
    ("unsignalized", "unsignalised"),
    ("yeild", "yield"),
    ("brak", "brake"),
    ("brke", "brake"),
    // Spellings that are words elsewhere but mean the driving word here, and planner
    // abbreviations.
    ("strait", "straight"),
    ("thru", "through"),
    ("jct", "junction"),
    ("jctn", "junction"),
    ("veh", "vehicle"),
    ("vehs", "vehicles"),
    ("ped", "pedestrian"),
    ("peds", "pedestrians"),
];

/// Splits an answer into sentences (lines, `.`, `!`, `?`, `;`), flattening JSON and markdown.
pub fn sentences(text: &str) -> Vec<Sentence> {
    sentences_with(text, &Speller::default())
}

/// [`sentences`] with a speller that knows more words.
pub fn sentences_with(text: &str, speller: &Speller) -> Vec<Sentence> {
    let flat = flatten_json(text).unwrap_or_else(|| text.to_string());
    let mut out = Vec::new();
    for line in flat.split('\n') {
        let line = strip_markup(line);
        if line.trim().is_empty() {
            continue;
        }
        for raw in split_sentences(&line) {
            let raw = raw.trim();
            if raw.is_empty() {
                continue;
            }
            let question = raw.ends_with('?');
            let norm = normalize_with(raw, speller);
            let words = words_of(&norm);
            if words.is_empty() {
                continue;
            }
            out.push(Sentence {
                original: raw.to_string(),
                norm,
                words,
                question,
            });
        }
    }
    out
}

/// JSON answers become `key: value` lines; nested keys are joined, arrays become comma lists,
/// booleans stay (`"brake": false` reads as a negation), and keys like `maybe` / `if_needed`
/// stay in front of their values as the hedges they are (G10).
fn flatten_json(text: &str) -> Option<String> {
    let t = text.trim();
    if !(t.starts_with('{') || t.starts_with('[')) {
        return None;
    }
    let v: serde_json::Value = serde_json::from_str(t).ok()?;
    let mut lines = Vec::new();
    fn walk(prefix: &str, v: &serde_json::Value, lines: &mut Vec<String>) {
        use serde_json::Value as V;
        match v {
            V::Object(m) => {
                for (k, x) in m {
                    let key = if prefix.is_empty() {
                        k.clone()
                    } else {
                        format!("{prefix} {k}")
                    };
                    walk(&key, x, lines);
                }
            }
            V::Array(a) => {
                let scalars: Vec<String> = a
                    .iter()
                    .filter_map(|x| match x {
                        V::String(s) => Some(s.clone()),
                        V::Bool(b) => Some(b.to_string()),
                        V::Number(n) => Some(n.to_string()),
                        _ => None,
                    })
                    .collect();
                if !scalars.is_empty() {
                    // One line per item keeps each item's own negation or hedge in its scope.
                    for s in scalars {
                        lines.push(if prefix.is_empty() {
                            s
                        } else {
                            format!("{prefix}: {s}")
                        });
                    }
                }
                for x in a.iter().filter(|x| x.is_object() || x.is_array()) {
                    walk(prefix, x, lines);
                }
            }
            V::String(s) => lines.push(format!("{prefix}: {s}")),
            V::Bool(b) => lines.push(format!("{prefix}: {b}")),
            V::Number(n) => lines.push(format!("{prefix}: {n}")),
            V::Null => lines.push(format!("{prefix}: none")),
        }
    }
    walk("", &v, &mut lines);
    Some(lines.join("\n"))
}

/// Drops markdown emphasis, headings and list markers.
fn strip_markup(line: &str) -> String {
    let mut s: String = line
        .chars()
        .map(|c| match c {
            '*' | '#' | '`' | '_' | '>' | '|' | '"' | '{' | '}' | '[' | ']' => ' ',
            '\u{2019}' | '\u{2018}' => '\'',
            '\u{201c}' | '\u{201d}' => ' ',
            '\u{2014}' | '\u{2013}' | '\u{2192}' | '\u{21d2}' | '\u{2022}' | '\u{00b7}' => ',',
            c => c,
        })
        .collect();
    s = s.replace("->", ",").replace("=>", ",");
    let t = s.trim_start();
    // List markers: "- ", "1.", "1)", "a)", "Step 1 -".
    let t = t.trim_start_matches(['-', '+']).trim_start();
    let mut t = t.to_string();
    let digits = t.chars().take_while(|c| c.is_ascii_digit()).count();
    if digits > 0 && digits < 3 {
        let rest = &t[digits..];
        if let Some(r) = rest.strip_prefix('.').or_else(|| rest.strip_prefix(')')) {
            if !r.starts_with(|c: char| c.is_ascii_digit()) {
                t = r.to_string();
            }
        }
    }
    let lower = t.to_lowercase();
    if let Some(r) = lower.strip_prefix("step ") {
        let d = r.chars().take_while(|c| c.is_ascii_digit()).count();
        if d > 0 {
            let r = r[d..].trim_start().trim_start_matches(['-', ':', '.', ')']);
            t = t[t.len() - r.len()..].to_string();
        }
    }
    t
}

/// Sentence boundaries: `.` (not in a number or an abbreviation), `!`, `?`, `;`.
fn split_sentences(line: &str) -> Vec<String> {
    let mut out = Vec::new();
    let mut cur = String::new();
    let chars: Vec<char> = line.chars().collect();
    for (i, &c) in chars.iter().enumerate() {
        cur.push(c);
        let end = match c {
            '!' | '?' | ';' => true,
            '.' => {
                let prev = i.checked_sub(1).map(|j| chars[j]);
                let next = chars.get(i + 1).copied();
                let in_number = prev.is_some_and(|p| p.is_ascii_digit())
                    && next.is_some_and(|n| n.is_ascii_digit());
                let lower = cur.to_lowercase();
                let last_word = lower
                    .rsplit(|c: char| c.is_whitespace() || c == '(')
                    .next()
                    .unwrap_or("");
                let abbrev = [
                    "e.g.", "i.e.", "etc.", "approx.", "vs.", "mr.", "mrs.", "st.", "no.",
                ]
                .contains(&last_word)
                    || next.is_some_and(|n| n.is_ascii_alphabetic());
                !in_number && !abbrev
            }
            _ => false,
        };
        if end {
            out.push(std::mem::take(&mut cur));
        }
    }
    if !cur.trim().is_empty() {
        out.push(cur);
    }
    out
}

/// Lower case, rewrites, punctuation split off, typos corrected.
pub fn normalize(s: &str) -> String {
    normalize_with(s, &Speller::default())
}

fn normalize_with(s: &str, speller: &Speller) -> String {
    let mut t = s.to_lowercase().replace('\u{2019}', "'");
    for (a, b) in REWRITES {
        if t.contains(a) {
            t = t.replace(a, b);
        }
    }
    let mut spaced = String::with_capacity(t.len() + 16);
    let chars: Vec<char> = t.chars().collect();
    for (i, &c) in chars.iter().enumerate() {
        match c {
            ',' | ';' | ':' | '(' | ')' | '?' | '!' | '=' | '/' | '+' | '&' | '~' | '\'' => {
                let rep = match c {
                    '+' | '&' => " and ",
                    '/' | '~' | '\'' => " ",
                    '=' => " is ",
                    _ => "",
                };
                if rep.is_empty() {
                    spaced.push(' ');
                    spaced.push(c);
                    spaced.push(' ');
                } else {
                    spaced.push_str(rep);
                }
            }
            '-' => {
                // Inside a word ("t-junction", "give-way") a hyphen is a space; alone it is a
                // clause break.
                let prev = i.checked_sub(1).map(|j| chars[j]);
                let next = chars.get(i + 1).copied();
                if prev.is_some_and(|p| p.is_alphanumeric())
                    && next.is_some_and(|n| n.is_alphanumeric())
                {
                    spaced.push(' ');
                } else {
                    spaced.push_str(" - ");
                }
            }
            '.' => {
                let prev = i.checked_sub(1).map(|j| chars[j]);
                let next = chars.get(i + 1).copied();
                if prev.is_some_and(|p| p.is_ascii_digit())
                    && next.is_some_and(|n| n.is_ascii_digit())
                {
                    spaced.push('.');
                } else {
                    spaced.push(' ');
                }
            }
            c if c.is_alphanumeric() || c.is_whitespace() => spaced.push(c),
            _ => spaced.push(' '),
        }
    }
    let typos: std::collections::HashMap<&str, &str> = TYPOS.iter().copied().collect();
    let mut words = Vec::new();
    for w in spaced.split_whitespace() {
        if let Some(r) = typos.get(w) {
            words.push((*r).to_string());
        } else if let Some(c) = speller.correct(w) {
            words.push(c.to_string());
        } else {
            words.push(w.to_string());
        }
    }
    words.join(" ")
}

fn words_of(norm: &str) -> Vec<Word> {
    let mut out = Vec::new();
    let mut pos = 0;
    for w in norm.split(' ') {
        if !w.is_empty() {
            out.push(Word {
                text: w.to_string(),
                start: pos,
                end: pos + w.len(),
            });
        }
        pos += w.len() + 1;
    }
    out
}

/// Does any of `seqs` (space-separated word sequences) start at word `i`? Returns its length.
pub fn seq_at(s: &Sentence, i: usize, seqs: &[&str]) -> Option<usize> {
    seqs.iter().find_map(|q| {
        let parts: Vec<&str> = q.split(' ').collect();
        (parts.iter().enumerate().all(|(k, p)| s.w(i + k) == *p)).then_some(parts.len())
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn typos_are_corrected_towards_the_domain_only() {
        assert_eq!(correct("intersecton"), Some("intersection"));
        assert_eq!(correct("pedestrain"), Some("pedestrian"));
        assert_eq!(correct("crosing"), Some("crossing"));
        assert_eq!(correct("roundabuot"), Some("roundabout"));
        assert_eq!(correct("sight"), None);
        assert_eq!(correct("night"), None);
        assert_eq!(correct("field"), None);
        assert_eq!(correct("the"), None);
        assert_eq!(
            normalize("slow dwon theres a zebra crosing just ahaed"),
            "slow down there is a zebra crossing just ahead"
        );
    }

    #[test]
    fn splits_sentences_lines_json_and_markdown() {
        let s = sentences("1. Scene: a T-junction, 2.5 m wide.\n2) Don't turn left; stop!\n**Why:** e.g. the light's red.");
        let n: Vec<&str> = s.iter().map(|x| x.norm.as_str()).collect();
        assert_eq!(
            n,
            vec![
                "scene : a t junction , 2.5 m wide",
                "do not turn left ;",
                "stop !",
                "why : e g the light is red",
            ]
        );
        let j = sentences(
            r#"{"scene": "urban", "actions": ["slow down"], "if_needed": ["stop"], "brake": false}"#,
        );
        let n: Vec<&str> = j.iter().map(|x| x.norm.as_str()).collect();
        assert!(n.contains(&"if needed : stop"), "{n:?}");
        assert!(n.contains(&"brake : false"), "{n:?}");
        assert!(n.contains(&"actions : slow down"), "{n:?}");
    }
}
