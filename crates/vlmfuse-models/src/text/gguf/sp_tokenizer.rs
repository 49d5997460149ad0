//! A SentencePiece-BPE encoder built from the vocabulary inside a GGUF file.
//!
//! The gemma GGUF ships no `tokenizer.json`; only `tokenizer.ggml.tokens`, `.scores` and
//! `.token_type`. Rather than guessing a greedy longest-match (which produces token sequences the
//! model never saw in training), this re-implements SentencePiece's BPE encoding: start from
//! characters, repeatedly merge the adjacent pair whose concatenation is a vocabulary piece with
//! the highest score (leftmost on ties), and fall back to `<0xXX>` byte pieces for characters not
//! in the vocabulary. The whole text is one sequence (no split at spaces), as llama.cpp and
//! transformers encode Gemma; `tests/gguf.rs` checks the ids against transformers on the real
//! 262k vocabulary.

use crate::ModelError;
use candle_core::quantized::gguf_file::{Content, Value};
use std::collections::HashMap;

const SPACE: char = '\u{2581}';

/// Token types as stored in `tokenizer.ggml.token_type` (llama.cpp's convention).
const TYPE_NORMAL: i32 = 1;
const TYPE_USER_DEFINED: i32 = 4;
const TYPE_BYTE: i32 = 6;

#[derive(Debug, Clone)]
pub struct SpTokenizer {
    pieces: Vec<String>,
    /// Pieces that BPE may produce (normal and user-defined), with their scores.
    merge: HashMap<String, (u32, f32)>,
    bytes: [Option<u32>; 256],
    bos: Option<u32>,
    add_space_prefix: bool,
}

fn md<'a>(ct: &'a Content, key: &str) -> Result<&'a Value, ModelError> {
    ct.metadata
        .get(key)
        .ok_or_else(|| ModelError::Tokenizer(format!("GGUF has no {key}")))
}

impl SpTokenizer {
    pub fn from_gguf(ct: &Content) -> Result<Self, ModelError> {
        let err = |e: candle_core::Error| ModelError::Tokenizer(e.to_string());
        let tokens = md(ct, "tokenizer.ggml.tokens")?.to_vec().map_err(err)?;
        let pieces: Vec<String> = tokens
            .iter()
            .map(|v| v.to_string().cloned())
            .collect::<Result<_, _>>()
            .map_err(err)?;
        let scores: Vec<f32> = match ct.metadata.get("tokenizer.ggml.scores") {
            Some(v) => v
                .to_vec()
                .map_err(err)?
                .iter()
                .map(|s| s.to_f32())
                .collect::<Result<_, _>>()
                .map_err(err)?,
            None => vec![0.0; pieces.len()],
        };
        let types: Vec<i32> = match ct.metadata.get("tokenizer.ggml.token_type") {
            Some(v) => v
                .to_vec()
                .map_err(err)?
                .iter()
                .map(|s| s.to_i32())
                .collect::<Result<_, _>>()
                .map_err(err)?,
            None => vec![TYPE_NORMAL; pieces.len()],
        };
        if scores.len() != pieces.len() || types.len() != pieces.len() {
            return Err(ModelError::Tokenizer(
                "GGUF tokens, scores and token types differ in length".into(),
            ));
        }
        let mut merge = HashMap::with_capacity(pieces.len());
        let mut bytes = [None; 256];
        for (i, p) in pieces.iter().enumerate() {
            match types[i] {
                TYPE_NORMAL | TYPE_USER_DEFINED => {
                    merge.entry(p.clone()).or_insert((i as u32, scores[i]));
                }
                TYPE_BYTE => {
                    if let Some(h) = p.strip_prefix("<0x").and_then(|s| s.strip_suffix('>')) {
                        if let Ok(b) = u8::from_str_radix(h, 16) {
                            bytes[b as usize] = Some(i as u32);
                        }
                    }
                }
                _ => {}
            }
        }
        let bos = ct
            .metadata
            .get("tokenizer.ggml.bos_token_id")
            .and_then(|v| v.to_u32().ok());
        let add_space_prefix = ct
            .metadata
            .get("tokenizer.ggml.add_space_prefix")
            .and_then(|v| v.to_bool().ok())
            .unwrap_or(false);
        Ok(Self {
            pieces,
            merge,
            bytes,
            bos,
            add_space_prefix,
        })
    }

    pub fn bos_id(&self) -> Option<u32> {
        self.bos
    }

    pub fn vocab_size(&self) -> usize {
        self.pieces.len()
    }

    /// The id of a piece as spelled in the vocabulary (spaces as U+2581), if it exists.
    pub fn piece_id(&self, piece: &str) -> Option<u32> {
        self.merge.get(piece).map(|(id, _)| *id)
    }

    pub fn piece(&self, id: u32) -> Option<&str> {
        self.pieces.get(id as usize).map(String::as_str)
    }

    /// Encodes text without BOS.
    pub fn encode(&self, text: &str) -> Vec<u32> {
        let mut norm: String = text.replace(' ', &SPACE.to_string());
        if self.add_space_prefix && !norm.starts_with(SPACE) {
            norm.insert(0, SPACE);
        }
        // The whole text is one BPE sequence, as in llama.cpp and transformers: Gemma's
        // vocabulary has pieces that span a space (`",▁"`), which splitting at spaces first
        // would never produce.
        let mut out = Vec::new();
        if !norm.is_empty() {
            self.encode_segment(&norm, &mut out);
        }
        out
    }

    fn lookup(&self, a: &str, b: &str) -> Option<(u32, f32)> {
        let mut s = String::with_capacity(a.len() + b.len());
        s.push_str(a);
        s.push_str(b);
        self.merge.get(&s).copied()
    }

    fn encode_segment(&self, seg: &str, out: &mut Vec<u32>) {
        let mut syms: Vec<String> = seg.chars().map(String::from).collect();
        let mut pair: Vec<Option<(u32, f32)>> = (0..syms.len().saturating_sub(1))
            .map(|i| self.lookup(&syms[i], &syms[i + 1]))
            .collect();
        loop {
            let mut best: Option<(usize, f32)> = None;
            for (i, p) in pair.iter().enumerate() {
                if let Some((_, s)) = p {
                    if best.is_none_or(|(_, bs)| *s > bs) {
                        best = Some((i, *s));
                    }
                }
            }
            let Some((i, _)) = best else { break };
            let right = syms.remove(i + 1);
            syms[i].push_str(&right);
            pair.remove(i);
            if i < pair.len() {
                pair[i] = self.lookup(&syms[i], &syms[i + 1]);
            }
            if i > 0 {
                pair[i - 1] = self.lookup(&syms[i - 1], &syms[i]);
            }
        }
        for s in syms {
            match self.merge.get(&s) {
                Some((id, _)) => out.push(*id),
                None => {
                    for b in s.bytes() {
                        if let Some(id) = self.bytes[b as usize] {
                            out.push(id);
                        }
                    }
                }
            }
        }
    }

    /// Decodes ids back to text (for debugging and tests).
    pub fn decode(&self, ids: &[u32]) -> String {
        let mut bytes = Vec::new();
        for &id in ids {
            let Some(p) = self.piece(id) else { continue };
            if let Some(b) = self
                .bytes
                .iter()
                .position(|x| *x == Some(id))
                .map(|b| b as u8)
            {
                bytes.push(b);
            } else {
                bytes.extend_from_slice(p.replace(SPACE, " ").as_bytes());
            }
        }
        String::from_utf8_lossy(&bytes).into_owned()
    }
}
