//! Constrained decoding: the model may only write `{"labels": [...]}` with distinct ontology ids.
//!
//! Why a mask and not a parser with retries: a small model (or a tiny random one) writes invalid
//! JSON or invented ids often, and a retry costs a whole generation. Masking the logits so that
//! only tokens which keep the output a prefix of some valid answer can be chosen makes an invalid
//! answer impossible, whatever the model. Each token consumes at least one byte and every id can
//! appear only once, so generation also ends within a bounded number of steps.
//!
//! The language is `{"labels": [` (item (`, ` item)*)? `]}` where an item is the JSON encoding
//! of an id. [`LabelGrammar`] is its byte-level automaton; [`TokenTrie`] holds the bytes of every
//! token that could ever be allowed (tokens spelled only with bytes of the language), so that one
//! depth-first walk per step finds all allowed tokens and prunes whole subtrees at the first
//! rejected byte.

use crate::llm::prompt::{ANSWER_CLOSE, ANSWER_OPEN};
use crate::LabelerError;

const SEP: &[u8] = b", ";

/// The byte-level automaton of the answer language for one ontology.
#[derive(Debug, Clone)]
pub struct LabelGrammar {
    /// JSON encodings of the ids (with their quotes), in ontology order.
    items: Vec<Vec<u8>>,
    open: Vec<u8>,
    close: Vec<u8>,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Phase {
    /// `open[..n]` written.
    Open(usize),
    /// After `[` or a separator: an item, or (only right after `[`) the close.
    ItemStart {
        first: bool,
    },
    /// `len` bytes of an item written.
    Item {
        len: usize,
    },
    /// After an item: a separator or the close.
    AfterItem,
    Sep(usize),
    Close(usize),
    Done,
}

/// Where the automaton is: the phase, the bytes of the item being written, and the ids used.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct GrammarState {
    phase: Phase,
    item: Vec<u8>,
    used: Vec<bool>,
    /// Ids completed so far, in the order written.
    written: Vec<usize>,
}

impl GrammarState {
    pub fn is_done(&self) -> bool {
        self.phase == Phase::Done
    }

    /// Ontology indices of the ids written so far, in order.
    pub fn written(&self) -> &[usize] {
        &self.written
    }
}

impl LabelGrammar {
    pub fn new<'a>(ids: impl IntoIterator<Item = &'a str>) -> Result<Self, LabelerError> {
        let items: Vec<Vec<u8>> = ids
            .into_iter()
            .map(|id| serde_json::to_string(id).map(String::into_bytes))
            .collect::<Result<_, _>>()
            .map_err(|e| LabelerError::Config(e.to_string()))?;
        if items.is_empty() {
            return Err(vlmfuse_core::OntologyError::Empty.into());
        }
        Ok(Self {
            items,
            open: ANSWER_OPEN.as_bytes().to_vec(),
            close: ANSWER_CLOSE.as_bytes().to_vec(),
        })
    }

    pub fn start(&self) -> GrammarState {
        GrammarState {
            phase: Phase::Open(0),
            item: Vec::new(),
            used: vec![false; self.items.len()],
            written: Vec::new(),
        }
    }

    /// Every byte any valid answer can contain.
    pub fn alphabet(&self) -> [bool; 256] {
        let mut a = [false; 256];
        for b in self
            .items
            .iter()
            .flatten()
            .chain(&self.open)
            .chain(&self.close)
            .chain(SEP)
        {
            a[*b as usize] = true;
        }
        a
    }

    /// Whether some unused item starts with `prefix`.
    fn item_prefix_ok(&self, used: &[bool], prefix: &[u8]) -> bool {
        self.items
            .iter()
            .zip(used)
            .any(|(it, &u)| !u && it.starts_with(prefix))
    }

    fn complete_item(&self, used: &[bool], bytes: &[u8]) -> Option<usize> {
        self.items
            .iter()
            .zip(used)
            .position(|(it, &u)| !u && it.as_slice() == bytes)
    }

    /// Advances by one byte in place; `false` (state unchanged in meaning, must be discarded)
    /// when the byte cannot follow.
    pub fn advance(&self, s: &mut GrammarState, b: u8) -> bool {
        match s.phase {
            Phase::Open(n) => {
                if self.open[n] != b {
                    return false;
                }
                s.phase = if n + 1 == self.open.len() {
                    Phase::ItemStart { first: true }
                } else {
                    Phase::Open(n + 1)
                };
                true
            }
            Phase::ItemStart { first } => {
                if first && self.close[0] == b {
                    s.phase = if self.close.len() == 1 {
                        Phase::Done
                    } else {
                        Phase::Close(1)
                    };
                    return true;
                }
                s.item.clear();
                s.item.push(b);
                if !self.item_prefix_ok(&s.used, &s.item) {
                    return false;
                }
                s.phase = Phase::Item { len: 1 };
                self.finish_item_if_complete(s);
                true
            }
            Phase::Item { len } => {
                s.item.push(b);
                if !self.item_prefix_ok(&s.used, &s.item) {
                    return false;
                }
                s.phase = Phase::Item { len: len + 1 };
                self.finish_item_if_complete(s);
                true
            }
            Phase::AfterItem => {
                if SEP[0] == b && s.used.iter().any(|u| !u) {
                    s.phase = if SEP.len() == 1 {
                        Phase::ItemStart { first: false }
                    } else {
                        Phase::Sep(1)
                    };
                    true
                } else if self.close[0] == b {
                    s.phase = if self.close.len() == 1 {
                        Phase::Done
                    } else {
                        Phase::Close(1)
                    };
                    true
                } else {
                    false
                }
            }
            Phase::Sep(n) => {
                if SEP[n] != b {
                    return false;
                }
                s.phase = if n + 1 == SEP.len() {
                    Phase::ItemStart { first: false }
                } else {
                    Phase::Sep(n + 1)
                };
                true
            }
            Phase::Close(n) => {
                if self.close[n] != b {
                    return false;
                }
                s.phase = if n + 1 == self.close.len() {
                    Phase::Done
                } else {
                    Phase::Close(n + 1)
                };
                true
            }
            Phase::Done => false,
        }
    }

    fn finish_item_if_complete(&self, s: &mut GrammarState) {
        // JSON strings cannot contain an unescaped quote, so a complete item is never a proper
        // prefix of another: completing is unambiguous.
        if let Some(k) = self.complete_item(&s.used, &s.item) {
            s.used[k] = true;
            s.written.push(k);
            s.item.clear();
            s.phase = Phase::AfterItem;
        }
    }

    /// Runs a whole byte string; `None` when it leaves the language.
    pub fn run(&self, s: &GrammarState, bytes: &[u8]) -> Option<GrammarState> {
        let mut t = s.clone();
        for &b in bytes {
            if !self.advance(&mut t, b) {
                return None;
            }
        }
        Some(t)
    }
}

/// A byte trie over the candidate tokens (those spelled only with bytes of the language).
pub struct TokenTrie {
    /// children[node]: (byte, child) sorted by byte.
    children: Vec<Vec<(u8, u32)>>,
    /// Tokens ending at a node.
    ends: Vec<Vec<u32>>,
}

impl TokenTrie {
    /// `spell(id)` gives the bytes of a token, `None` for tokens that must never be generated.
    pub fn build<'a>(
        vocab_size: usize,
        spell: impl Fn(u32) -> Option<&'a [u8]>,
        alphabet: &[bool; 256],
    ) -> Self {
        let mut t = TokenTrie {
            children: vec![Vec::new()],
            ends: vec![Vec::new()],
        };
        for id in 0..vocab_size as u32 {
            let Some(bytes) = spell(id) else { continue };
            if bytes.is_empty() || !bytes.iter().all(|&b| alphabet[b as usize]) {
                continue;
            }
            let mut node = 0usize;
            for &b in bytes {
                node = match t.children[node].binary_search_by_key(&b, |c| c.0) {
                    Ok(i) => t.children[node][i].1 as usize,
                    Err(i) => {
                        let new = t.children.len();
                        t.children.push(Vec::new());
                        t.ends.push(Vec::new());
                        t.children[node].insert(i, (b, new as u32));
                        new
                    }
                };
            }
            t.ends[node].push(id);
        }
        t
    }

    /// Number of candidate tokens.
    pub fn len(&self) -> usize {
        self.ends.iter().map(Vec::len).sum()
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Whether every byte of the language is a token on its own, which guarantees that every
    /// non-final state has at least one allowed token.
    pub fn spells_every_byte(&self, alphabet: &[bool; 256]) -> Result<(), u8> {
        for b in 0..=255u8 {
            if !alphabet[b as usize] {
                continue;
            }
            let ok = self.children[0]
                .binary_search_by_key(&b, |c| c.0)
                .is_ok_and(|i| !self.ends[self.children[0][i].1 as usize].is_empty());
            if !ok {
                return Err(b);
            }
        }
        Ok(())
    }

    /// Every candidate token allowed in state `s`, with the state after it.
    pub fn allowed(&self, g: &LabelGrammar, s: &GrammarState) -> Vec<(u32, GrammarState)> {
        let mut out = Vec::new();
        let mut stack: Vec<(usize, GrammarState)> = vec![(0, s.clone())];
        while let Some((node, st)) = stack.pop() {
            for &(b, child) in &self.children[node] {
                let mut next = st.clone();
                if !g.advance(&mut next, b) {
                    continue;
                }
                for &id in &self.ends[child as usize] {
                    out.push((id, next.clone()));
                }
                if !next.is_done() && !self.children[child as usize].is_empty() {
                    stack.push((child as usize, next));
                }
            }
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn g() -> LabelGrammar {
        LabelGrammar::new(["brake", "stop", "turn_left", "turn_right"]).unwrap()
    }

    #[test]
    fn accepts_exactly_the_answer_language() {
        let g = g();
        let ok = |s: &str| g.run(&g.start(), s.as_bytes()).is_some_and(|t| t.is_done());
        assert!(ok(r#"{"labels": []}"#));
        assert!(ok(r#"{"labels": ["brake"]}"#));
        assert!(ok(r#"{"labels": ["turn_right", "brake", "stop"]}"#));
        assert!(!ok(r#"{"labels": ["brake", "brake"]}"#), "duplicate");
        assert!(!ok(r#"{"labels": ["fly"]}"#));
        assert!(!ok(r#"{"labels": ["turn"]}"#));
        assert!(!ok(r#"{"labels": [, "stop"]}"#));
        assert!(!ok(r#"{"labels": ["stop",]}"#));
        assert!(!ok(r#"{"labels":["stop"]}"#));
        assert!(!ok(r#"{"labels": ["stop"]} "#), "nothing after the close");
        // Prefixes are live but not done.
        let t = g.run(&g.start(), br#"{"labels": ["turn_"#).unwrap();
        assert!(!t.is_done());
        // All four used: no separator can follow.
        let t = g
            .run(
                &g.start(),
                br#"{"labels": ["brake", "stop", "turn_left", "turn_right""#,
            )
            .unwrap();
        assert!(g.run(&t, b",").is_none());
        assert!(g.run(&t, b"]}").unwrap().is_done());
        let t = g
            .run(&g.start(), br#"{"labels": ["stop", "brake"]}"#)
            .unwrap();
        assert_eq!(t.written(), &[1, 0]);
    }

    #[test]
    fn trie_finds_multi_byte_tokens_and_prunes() {
        let g = g();
        let vocab: Vec<&[u8]> = vec![
            b"{", b"\"", b"labels", b"\":", b" [", b"[", b"]", b"}", b",", b" ", b"brake", b"stop",
            b"turn", b"_", b"left", b"right", b"\"]}", b"l", b"a", b"b", b"e", b"s", b":", b"k",
            b"r", b"t", b"o", b"p", b"u", b"n", b"f", b"i", b"g", b"h", b"x", b"xyz",
        ];
        let alpha = g.alphabet();
        let trie = TokenTrie::build(vocab.len(), |i| Some(vocab[i as usize]), &alpha);
        // "x" and "xyz" use bytes outside the language.
        assert_eq!(trie.len(), vocab.len() - 2);
        trie.spells_every_byte(&alpha).unwrap();
        let s = g.run(&g.start(), br#"{"labels": [""#).unwrap();
        let mut ids: Vec<&[u8]> = trie
            .allowed(&g, &s)
            .iter()
            .map(|(i, _)| vocab[*i as usize])
            .collect();
        ids.sort();
        assert_eq!(ids, vec![&b"b"[..], b"brake", b"s", b"stop", b"t", b"turn"]);
        let s = g.run(&g.start(), br#"{"labels": ["stop"#).unwrap();
        let ids: Vec<&[u8]> = trie
            .allowed(&g, &s)
            .iter()
            .map(|(i, _)| vocab[*i as usize])
            .collect();
        assert!(ids.contains(&&b"\"]}"[..]) && ids.contains(&&b"\""[..]));
    }

    /// Whatever the model prefers (here: random logits, fresh every step, over a vocabulary
    /// with multi-byte tokens that straddle the structure), greedy constrained decoding ends
    /// with a valid answer within a bounded number of steps.
    #[test]
    fn any_model_yields_a_valid_answer() {
        let ids = ["turn_left", "turn_right", "brake", "stop", "a\"b"];
        let g = LabelGrammar::new(ids).unwrap();
        let mut vocab: Vec<Vec<u8>> = (0u8..=255).map(|b| vec![b]).collect();
        for t in [
            "{\"", "labels", "\": [", "[\"", "\", \"", "\"]}", "]}", "turn", "_left", "_right",
            "bra", "ke\"", "stop\"", "\\\"", "ab", "xyz",
        ] {
            vocab.push(t.as_bytes().to_vec());
        }
        let alpha = g.alphabet();
        let trie = TokenTrie::build(vocab.len(), |i| Some(vocab[i as usize].as_slice()), &alpha);
        trie.spells_every_byte(&alpha).unwrap();
        let mut seed = 12345u64;
        let mut rnd = || {
            seed ^= seed << 13;
            seed ^= seed >> 7;
            seed ^= seed << 17;
            (seed >> 11) as f64 / (1u64 << 53) as f64
        };
        for _ in 0..300 {
            let mut st = g.start();
            let mut out = Vec::new();
            let mut steps = 0;
            while !st.is_done() {
                let allowed = trie.allowed(&g, &st);
                assert!(
                    !allowed.is_empty(),
                    "stuck after {:?}",
                    String::from_utf8_lossy(&out)
                );
                let pick = allowed
                    .iter()
                    .map(|(id, s)| (rnd(), *id, s.clone()))
                    .max_by(|a, b| a.0.total_cmp(&b.0))
                    .unwrap();
                out.extend_from_slice(&vocab[pick.1 as usize]);
                st = pick.2;
                steps += 1;
                assert!(steps < 200, "no end");
            }
            let text = String::from_utf8(out).unwrap();
            let v: serde_json::Value =
                serde_json::from_str(&text).unwrap_or_else(|e| panic!("{text}: {e}"));
            let labels: Vec<&str> = v["labels"]
                .as_array()
                .unwrap()
                .iter()
                .map(|x| x.as_str().unwrap())
                .collect();
            let mut uniq = labels.clone();
            uniq.sort();
            uniq.dedup();
            assert_eq!(uniq.len(), labels.len(), "{text}");
            assert!(labels.iter().all(|l| ids.contains(l)), "{text}");
        }
    }
}
