//! A SentencePiece-BPE encoder built from the vocabulary inside a GGUF file.
//!
//! The gemma GGUF ships no `tokenizer.json`; only `tokenizer.ggml.tokens`, `.scores` and
//! `.token_type`. SentencePiece's BPE repeatedly merges the adjacent pair whose concatenation is a
//! vocabulary piece with the highest score, and falls back to `<0xXX>` byte pieces for characters
//! not in the vocabulary. The `tokenizers` crate's BPE model runs exactly that once it is given
//! merges ranked by score: as transformers' converter does for SentencePiece vocabularies, every
//! split of a piece into two vocabulary pieces is a merge, ranked by the piece's score (then by
//! the ids, for a stable order), with byte fallback on. The whole text is one sequence (no split
//! at spaces), as llama.cpp and transformers encode Gemma; `tests/gguf.rs` checks the ids
//! against transformers on the real 262k vocabulary.

use crate::ModelError;
use candle_core::quantized::gguf_file::{Content, Value};
use std::collections::HashMap;
use tokenizers::models::bpe::BPE;
use tokenizers::Model;

const SPACE: char = '\u{2581}';

/// Token types as stored in `tokenizer.ggml.token_type` (llama.cpp's convention).
const TYPE_NORMAL: i32 = 1;
const TYPE_USER_DEFINED: i32 = 4;
const TYPE_BYTE: i32 = 6;

#[derive(Clone)]
pub struct SpTokenizer {
    pieces: Vec<String>,
    /// Pieces that BPE may produce (normal and user-defined): their ids.
    ids: HashMap<String, u32>,
    bpe: BPE,
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
        let mut ids: HashMap<String, u32> = HashMap::with_capacity(pieces.len());
        let mut bytes = [None; 256];
        for (i, p) in pieces.iter().enumerate() {
            match types[i] {
                TYPE_NORMAL | TYPE_USER_DEFINED => {
                    ids.entry(p.clone()).or_insert(i as u32);
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
        // Every way to build a mergeable piece from two mergeable pieces, best score first.
        let mut ranked: Vec<(f32, u32, u32, u32)> = Vec::new();
        for (p, &id) in &ids {
            for (k, _) in p.char_indices().skip(1) {
                let (l, r) = p.split_at(k);
                if let (Some(&li), Some(&ri)) = (ids.get(l), ids.get(r)) {
                    ranked.push((scores[id as usize], id, li, ri));
                }
            }
        }
        ranked.sort_by(|a, b| {
            b.0.total_cmp(&a.0)
                .then(a.1.cmp(&b.1))
                .then(a.2.cmp(&b.2))
                .then(a.3.cmp(&b.3))
        });
        let merges: Vec<(String, String)> = ranked
            .iter()
            .map(|&(_, _, l, r)| (pieces[l as usize].clone(), pieces[r as usize].clone()))
            .collect();
        // The BPE vocabulary: mergeable pieces and byte pieces (what byte fallback emits).
        let vocab: tokenizers::models::bpe::Vocab = ids
            .iter()
            .map(|(p, &i)| (p.clone(), i))
            .chain(
                bytes
                    .iter()
                    .flatten()
                    .map(|&i| (pieces[i as usize].clone(), i)),
            )
            .collect();
        let bpe = BPE::builder()
            .vocab_and_merges(vocab, merges)
            .byte_fallback(true)
            .build()
            .map_err(|e| ModelError::Tokenizer(e.to_string()))?;
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
            ids,
            bpe,
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
        self.ids.get(piece).copied()
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
        if norm.is_empty() {
            return Vec::new();
        }
        match self.bpe.tokenize(&norm) {
            Ok(tokens) => tokens.into_iter().map(|t| t.id).collect(),
            // Byte fallback covers every character, so BPE has no failure left but a bug;
            // an empty encoding would silently drop the text, so spell it in bytes instead.
            Err(_) => norm
                .bytes()
                .filter_map(|b| self.bytes[b as usize])
                .collect(),
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
