//! The tokenizer a GGUF file describes, built from its own metadata: GGUF files carry no
//! `tokenizer.json`, only llama.cpp's `tokenizer.ggml.*` keys.
//!
//! * `tokenizer.ggml.model = "gpt2"` (Llama 3.x, Qwen2/3): byte-level BPE with the file's
//!   merges. The `tokenizers` crate runs it, with the pre-tokenizer split regex chosen by
//!   `tokenizer.ggml.pre`, the same choice transformers and llama.cpp make.
//! * `tokenizer.ggml.model = "llama"` (Gemma 3): SentencePiece BPE over scores, [`SpTokenizer`].
//!
//! Both match control tokens (`<start_of_turn>`, `<|eot_id|>`, ...) and user-defined tokens
//! (Gemma's `"\n\n"`) whole in the rendered chat prompt, as llama.cpp does. Control tokens are
//! removed from untrusted text before it enters the prompt, so that an answer cannot close the
//! user turn early.
//!
//! The constrained decoder needs the bytes each token spells; [`GgufTokenizer::token_bytes`]
//! gives them (`None` for control tokens, which never appear in an answer).

use super::sp_tokenizer::SpTokenizer;
use crate::ModelError;
use aho_corasick::{AhoCorasick, MatchKind};
use candle_core::quantized::gguf_file::{Content, Value};
use std::collections::HashMap;
use tokenizers::models::bpe::BPE;
use tokenizers::pre_tokenizers::byte_level::ByteLevel;
use tokenizers::pre_tokenizers::sequence::Sequence;
use tokenizers::pre_tokenizers::split::{Split, SplitPattern};
use tokenizers::{AddedToken, SplitDelimiterBehavior, Tokenizer};

/// llama.cpp's token types (`tokenizer.ggml.token_type`).
const TYPE_CONTROL: i32 = 3;
const TYPE_USER_DEFINED: i32 = 4;
const TYPE_BYTE: i32 = 6;

/// Llama 3's pre-tokenizer split (also used by transformers for `llama-bpe` and friends).
const LLAMA3_SPLIT: &str = r"(?i:'s|'t|'re|'ve|'m|'ll|'d)|[^\r\n\p{L}\p{N}]?\p{L}+|\p{N}{1,3}| ?[^\s\p{L}\p{N}]+[\r\n]*|\s*[\r\n]+|\s+(?!\S)|\s+";
/// Qwen2/Qwen3's split: as Llama 3's, but digits one at a time.
const QWEN2_SPLIT: &str = r"(?i:'s|'t|'re|'ve|'m|'ll|'d)|[^\r\n\p{L}\p{N}]?\p{L}+|\p{N}| ?[^\s\p{L}\p{N}]+[\r\n]*|\s*[\r\n]+|\s+(?!\S)|\s+";

fn split_regex(pre: &str) -> Option<&'static str> {
    match pre {
        "llama3" | "llama-v3" | "llama-bpe" | "smaug-bpe" | "dbrx" => Some(LLAMA3_SPLIT),
        "qwen2" | "deepseek-r1-qwen" => Some(QWEN2_SPLIT),
        _ => None,
    }
}

/// GPT-2's reversible byte ↔ printable-character table used by byte-level BPE vocabularies.
pub fn bytes_to_unicode() -> [char; 256] {
    let mut table = ['\0'; 256];
    let mut extra = 0u32;
    for b in 0..256u32 {
        let printable =
            (33..=126).contains(&b) || (161..=172).contains(&b) || (174..=255).contains(&b);
        table[b as usize] = if printable {
            char::from_u32(b).unwrap_or('\0')
        } else {
            let c = char::from_u32(256 + extra).unwrap_or('\0');
            extra += 1;
            c
        };
    }
    table
}

fn md<'a>(ct: &'a Content, key: &str) -> Option<&'a Value> {
    ct.metadata.get(key)
}

fn md_strings(ct: &Content, key: &str) -> Result<Vec<String>, ModelError> {
    let err = |e: candle_core::Error| ModelError::Tokenizer(format!("{key}: {e}"));
    md(ct, key)
        .ok_or_else(|| ModelError::Tokenizer(format!("GGUF has no {key}")))?
        .to_vec()
        .map_err(err)?
        .iter()
        .map(|v| v.to_string().cloned().map_err(err))
        .collect()
}

fn md_types(ct: &Content, n: usize) -> Result<Vec<i32>, ModelError> {
    match md(ct, "tokenizer.ggml.token_type") {
        None => Ok(vec![1; n]),
        Some(v) => {
            let err = |e: candle_core::Error| ModelError::Tokenizer(format!("token_type: {e}"));
            let t: Vec<i32> = v
                .to_vec()
                .map_err(err)?
                .iter()
                .map(|x| x.to_i32().map_err(err))
                .collect::<Result<_, _>>()?;
            if t.len() != n {
                return Err(ModelError::Tokenizer(
                    "GGUF tokens and token types differ in length".into(),
                ));
            }
            Ok(t)
        }
    }
}

enum Engine {
    Bpe(Box<Tokenizer>),
    Sp {
        sp: Box<SpTokenizer>,
        /// Control and user-defined tokens, matched whole, longest first.
        specials: AhoCorasick,
        special_ids: Vec<u32>,
    },
}

/// A GGUF model's tokenizer (see the module docs).
pub struct GgufTokenizer {
    engine: Engine,
    tokens: Vec<String>,
    token_bytes: Vec<Option<Vec<u8>>>,
    control: Vec<String>,
    bos: Option<u32>,
    eos: Option<u32>,
    add_bos: bool,
}

impl GgufTokenizer {
    pub fn from_gguf(ct: &Content) -> Result<Self, ModelError> {
        let model = md(ct, "tokenizer.ggml.model")
            .and_then(|v| v.to_string().ok())
            .cloned()
            .unwrap_or_else(|| "llama".into());
        let tokens = md_strings(ct, "tokenizer.ggml.tokens")?;
        let types = md_types(ct, tokens.len())?;
        let id_of = |key: &str| md(ct, key).and_then(|v| v.to_u32().ok());
        let bos = id_of("tokenizer.ggml.bos_token_id");
        let eos = id_of("tokenizer.ggml.eos_token_id");
        let control: Vec<String> = tokens
            .iter()
            .zip(&types)
            .filter(|(_, &t)| t == TYPE_CONTROL)
            .map(|(s, _)| s.clone())
            .collect();
        let (engine, token_bytes, default_add_bos) = match model.as_str() {
            "gpt2" => {
                let merges = md_strings(ct, "tokenizer.ggml.merges")?;
                let pre = md(ct, "tokenizer.ggml.pre")
                    .and_then(|v| v.to_string().ok())
                    .cloned()
                    .unwrap_or_default();
                let (tok, bytes) = build_bpe(&tokens, &types, &merges, &pre)?;
                (Engine::Bpe(Box::new(tok)), bytes, false)
            }
            "llama" => {
                let sp = SpTokenizer::from_gguf(ct)?;
                let mut pats = Vec::new();
                let mut special_ids = Vec::new();
                for (i, (s, &t)) in tokens.iter().zip(&types).enumerate() {
                    if (t == TYPE_CONTROL || t == TYPE_USER_DEFINED) && !s.is_empty() {
                        pats.push(s.clone());
                        special_ids.push(i as u32);
                    }
                }
                let specials = AhoCorasick::builder()
                    .match_kind(MatchKind::LeftmostLongest)
                    .build(&pats)
                    .map_err(|e| ModelError::Tokenizer(e.to_string()))?;
                let bytes = tokens
                    .iter()
                    .zip(&types)
                    .map(|(s, &t)| match t {
                        TYPE_CONTROL => None,
                        TYPE_BYTE => s
                            .strip_prefix("<0x")
                            .and_then(|h| h.strip_suffix('>'))
                            .and_then(|h| u8::from_str_radix(h, 16).ok())
                            .map(|b| vec![b]),
                        _ => Some(s.replace('\u{2581}', " ").into_bytes()),
                    })
                    .collect();
                (
                    Engine::Sp {
                        sp: Box::new(sp),
                        specials,
                        special_ids,
                    },
                    bytes,
                    true,
                )
            }
            other => {
                return Err(ModelError::Tokenizer(format!(
                    "unsupported GGUF tokenizer model {other:?} (supported: gpt2 byte-level BPE, \
                     llama SentencePiece)"
                )))
            }
        };
        let add_bos = md(ct, "tokenizer.ggml.add_bos_token")
            .and_then(|v| v.to_bool().ok())
            .unwrap_or(default_add_bos);
        Ok(Self {
            engine,
            tokens,
            token_bytes,
            control,
            bos,
            eos,
            add_bos,
        })
    }

    pub fn vocab_size(&self) -> usize {
        self.tokens.len()
    }

    /// The token's spelling in the vocabulary (for templates: `bos_token`, `eos_token`).
    pub fn token_str(&self, id: u32) -> Option<&str> {
        self.tokens.get(id as usize).map(String::as_str)
    }

    pub fn bos_id(&self) -> Option<u32> {
        self.bos
    }

    pub fn eos_id(&self) -> Option<u32> {
        self.eos
    }

    /// Whether the file asks for a BOS token at the start of a prompt.
    pub fn add_bos(&self) -> bool {
        self.add_bos
    }

    /// The bytes a token stands for in generated text; `None` for control tokens.
    pub fn token_bytes(&self, id: u32) -> Option<&[u8]> {
        self.token_bytes.get(id as usize)?.as_deref()
    }

    /// Removes control-token spellings from untrusted text (see the module docs).
    pub fn strip_control(&self, text: &str) -> String {
        let mut s = text.to_string();
        for c in &self.control {
            if s.contains(c.as_str()) {
                s = s.replace(c.as_str(), "");
            }
        }
        s
    }

    /// Encodes a rendered prompt, matching control and user-defined tokens whole. Adds BOS when
    /// the file asks for it and the text does not start with it already.
    pub fn encode_prompt(&self, text: &str) -> Result<Vec<u32>, ModelError> {
        let mut ids = match &self.engine {
            Engine::Bpe(tok) => tok
                .encode(text, false)
                .map_err(|e| ModelError::Tokenizer(e.to_string()))?
                .get_ids()
                .to_vec(),
            Engine::Sp {
                sp,
                specials,
                special_ids,
            } => {
                let mut out = Vec::new();
                let mut last = 0;
                for m in specials.find_iter(text) {
                    if m.start() > last {
                        out.extend(sp.encode(&text[last..m.start()]));
                    }
                    out.push(special_ids[m.pattern().as_usize()]);
                    last = m.end();
                }
                if last < text.len() {
                    out.extend(sp.encode(&text[last..]));
                }
                out
            }
        };
        if self.add_bos {
            if let Some(b) = self.bos {
                if ids.first() != Some(&b) {
                    ids.insert(0, b);
                }
            }
        }
        Ok(ids)
    }

    /// Decodes generated ids (control tokens are dropped).
    pub fn decode(&self, ids: &[u32]) -> String {
        let bytes: Vec<u8> = ids
            .iter()
            .filter_map(|&i| self.token_bytes(i))
            .flatten()
            .copied()
            .collect();
        String::from_utf8_lossy(&bytes).into_owned()
    }
}

type BpeBuild = (Tokenizer, Vec<Option<Vec<u8>>>);

fn build_bpe(
    tokens: &[String],
    types: &[i32],
    merges: &[String],
    pre: &str,
) -> Result<BpeBuild, ModelError> {
    let terr = |e: tokenizers::Error| ModelError::Tokenizer(e.to_string());
    let b2u = bytes_to_unicode();
    let u2b: HashMap<char, u8> = b2u.iter().enumerate().map(|(b, &c)| (c, b as u8)).collect();
    let in_alphabet = |s: &str| s.chars().all(|c| u2b.contains_key(&c));
    // A token outside the byte alphabet (some files store added tokens raw) is respelled in it,
    // so that the BPE model and the added-token matcher agree on it.
    let spelled: Vec<String> = tokens
        .iter()
        .map(|t| {
            if in_alphabet(t) {
                t.clone()
            } else {
                t.bytes().map(|b| b2u[b as usize]).collect()
            }
        })
        .collect();
    let vocab: tokenizers::models::bpe::Vocab = spelled
        .iter()
        .enumerate()
        .map(|(i, t)| (t.clone(), i as u32))
        .collect();
    let merges: Vec<(String, String)> = merges
        .iter()
        .map(|m| {
            m.split_once(' ')
                .map(|(a, b)| (a.to_string(), b.to_string()))
                .ok_or_else(|| ModelError::Tokenizer(format!("malformed merge {m:?}")))
        })
        .collect::<Result<_, _>>()?;
    let bpe = BPE::builder()
        .vocab_and_merges(vocab, merges)
        .build()
        .map_err(terr)?;
    let mut tok = Tokenizer::new(bpe);
    match split_regex(pre) {
        Some(re) => {
            let split = Split::new(
                SplitPattern::Regex(re.to_string()),
                SplitDelimiterBehavior::Isolated,
                false,
            )
            .map_err(terr)?;
            let bl = ByteLevel::new(false, true, false);
            tok.with_pre_tokenizer(Some(Sequence::new(vec![split.into(), bl.into()])));
        }
        None => {
            tok.with_pre_tokenizer(Some(ByteLevel::new(false, true, true)));
        }
    }
    tok.with_decoder(Some(ByteLevel::default()));
    let control: Vec<AddedToken> = tokens
        .iter()
        .zip(types)
        .filter(|(t, &ty)| ty == TYPE_CONTROL && in_alphabet(t))
        .map(|(t, _)| AddedToken::from(t.clone(), true).normalized(false))
        .collect();
    tok.add_special_tokens(control).map_err(terr)?;
    // As transformers does: a user-defined token spelled outside the byte alphabet was respelled
    // above and is left to the BPE model.
    let user: Vec<AddedToken> = tokens
        .iter()
        .zip(types)
        .filter(|(t, &ty)| ty == TYPE_USER_DEFINED && in_alphabet(t))
        .map(|(t, _)| AddedToken::from(t.clone(), false).normalized(false))
        .collect();
    tok.add_tokens(user).map_err(terr)?;
    let bytes = spelled
        .iter()
        .zip(types)
        .map(|(t, &ty)| {
            if ty == TYPE_CONTROL {
                None
            } else {
                t.chars().map(|c| u2b.get(&c).copied()).collect()
            }
        })
        .collect();
    Ok((tok, bytes))
}

#[cfg(test)]
mod tests {
    use super::bytes_to_unicode;

    #[test]
    fn byte_table_is_gpt2s() {
        let t = bytes_to_unicode();
        assert_eq!(t[b'a' as usize], 'a');
        assert_eq!(t[b' ' as usize], 'Ġ');
        assert_eq!(t[b'\n' as usize], 'Ċ');
        let mut all: Vec<char> = t.to_vec();
        all.sort();
        all.dedup();
        assert_eq!(all.len(), 256);
    }
}
