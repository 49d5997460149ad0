//! Tiny random-weight GGUF files in the real layout of each supported family, for tests.
//!
//! Why: tests never download weights, yet the GGUF labeler must be exercised end to end (file
//! parsing, tokenizer from metadata, chat template, model forward, constrained decoding) for every
//! family. These files have the real metadata keys, tensor names and tokenizer kinds of Llama 3,
//! Qwen2, Qwen3 and Gemma 3, with a few hundred tokens and two layers of 64 dimensions, and are
//! byte-for-byte deterministic for a seed, so that reference outputs computed once by
//! transformers (`tests/data/labeler/gguf/reference.py`) stay valid.
//!
//! Test tooling, not library API: it moves to the test-kit crate with `assets` and `eval`.

use crate::llm::template::{fallback_template, TemplateFamily};
use crate::LabelerError;
use candle_core::quantized::gguf_file::{self, Value};
use candle_core::quantized::{GgmlDType, QTensor};
use candle_core::{Device, Tensor};
use std::collections::HashSet;
use std::path::Path;
use vlmfuse_models::text::gguf::bytes_to_unicode;
use vlmfuse_models::text::gguf::Family;

/// Words the vocabularies learn merges for: the answer format, the default ontology's ids, the
/// prompt's frequent words. Any text still encodes (bytes / byte fallback); these only make the
/// token sequences realistic (multi-byte tokens, merges that cross `_`).
const WORDS: &[&str] = &[
    "{\"",
    "labels",
    "\":",
    " [",
    "[\"",
    "\"]",
    "]}",
    "\", \"",
    ", ",
    "\"",
    "turn",
    "_left",
    "_right",
    "left",
    "right",
    "turn_left",
    "turn_right",
    "brake",
    "accelerate",
    "stop",
    "traffic",
    "_light",
    "_ahead",
    "light",
    "ahead",
    "junction",
    "pedestrian",
    "_crossing",
    "crossing",
    "merge",
    "maintain",
    "_safe",
    "_distance",
    "check",
    "_blind",
    "_spot",
    "adjust",
    "_speed",
    "_due",
    "_to",
    "_weather",
    "yield",
    "_traffic",
    "drive",
    "_as",
    "_normal",
    " the",
    " a",
    " to",
    " and",
    " is",
    " of",
    " text",
    " label",
    " labels",
    " driving",
    " car",
    " slow",
    " down",
    " red",
    " at",
    " for",
    " You",
    " Answer",
    " JSON",
    " with",
    " only",
    "Text",
    "system",
    "user",
    "assistant",
    "model",
    "\n\n",
    " Brake",
    " Stop",
    " Turn",
    " now",
    " light",
];

/// The seed of the files `tests/data/labeler/gguf/reference.json` was computed on.
pub const PARITY_SEED: u64 = 7;

/// Dimensions of the tiny models.
const HIDDEN: usize = 64;
const HEADS: usize = 4;
const KV_HEADS: usize = 2;
const HEAD_DIM: usize = 16;
const FFN: usize = 128;
const LAYERS: usize = 2;
/// Gemma 3 scales attention by 1/sqrt(head_dim) in candle and llama.cpp, by
/// 1/sqrt(query_pre_attn_scalar) (256 in the released configs) in transformers; the reference
/// script sets the latter to this head size so that both compute the same model.
const GEMMA_HEAD_DIM: usize = 32;

/// Deterministic uniform numbers (splitmix64), so that a seed gives the same file everywhere.
struct Rng(u64);

impl Rng {
    fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform in [-a, a).
    fn uniform(&mut self, a: f32) -> f32 {
        let u = (self.next_u64() >> 40) as f32 / (1u64 << 24) as f32;
        (2.0 * u - 1.0) * a
    }
}

struct Vocab {
    tokens: Vec<String>,
    types: Vec<i32>,
    scores: Vec<f32>,
    merges: Vec<String>,
    bos: u32,
    eos: u32,
}

/// Byte-level BPE vocabulary: the 256 byte symbols, merges that build [`WORDS`] left to right,
/// then the family's special tokens.
fn bpe_vocab(specials: &[(&str, i32)], bos: &str, eos: &str) -> Vocab {
    let b2u = bytes_to_unicode();
    let mut tokens: Vec<String> = b2u.iter().map(|c| c.to_string()).collect();
    let mut seen: HashSet<String> = tokens.iter().cloned().collect();
    let mut merges = Vec::new();
    for w in WORDS {
        let chars: Vec<String> = w.bytes().map(|b| b2u[b as usize].to_string()).collect();
        let mut acc = chars[0].clone();
        for c in &chars[1..] {
            let joined = format!("{acc}{c}");
            if seen.insert(joined.clone()) {
                merges.push(format!("{acc} {c}"));
                tokens.push(joined.clone());
            }
            acc = joined;
        }
    }
    let mut types = vec![1; tokens.len()];
    for (s, t) in specials {
        tokens.push(s.to_string());
        types.push(*t);
    }
    let id = |s: &str| tokens.iter().position(|t| t == s).unwrap_or(0) as u32;
    let (bos, eos) = (id(bos), id(eos));
    let n = tokens.len();
    Vocab {
        tokens,
        types,
        scores: vec![0.0; n],
        merges,
        bos,
        eos,
    }
}

/// SentencePiece vocabulary in Gemma's layout: control tokens, byte pieces, characters, then
/// word pieces, scored by position (earlier merges first), which is also how transformers
/// rebuilds Gemma's merges from a GGUF.
fn sp_vocab() -> Vocab {
    let mut tokens: Vec<String> = Vec::new();
    let mut types = Vec::new();
    for s in [
        "<pad>",
        "<eos>",
        "<bos>",
        "<unk>",
        "<start_of_turn>",
        "<end_of_turn>",
    ] {
        tokens.push(s.into());
        types.push(3);
    }
    for s in ["\n", "\n\n"] {
        tokens.push(s.into());
        types.push(4);
    }
    for b in 0..=255u8 {
        tokens.push(format!("<0x{b:02X}>"));
        types.push(6);
    }
    let mut seen: HashSet<String> = tokens.iter().cloned().collect();
    let mut push = |s: String, tokens: &mut Vec<String>, types: &mut Vec<i32>| {
        if seen.insert(s.clone()) {
            tokens.push(s);
            types.push(1);
        }
    };
    push("\u{2581}".into(), &mut tokens, &mut types);
    for c in (b' '..=b'~').map(char::from).filter(|c| *c != ' ') {
        push(c.to_string(), &mut tokens, &mut types);
    }
    for w in WORDS {
        let w = w.replace(' ', "\u{2581}");
        if w.contains('\n') {
            continue;
        }
        let chars: Vec<char> = w.chars().collect();
        let mut acc = chars[0].to_string();
        for c in &chars[1..] {
            acc.push(*c);
            push(acc.clone(), &mut tokens, &mut types);
        }
    }
    let n = tokens.len();
    Vocab {
        scores: (0..n).map(|i| -(i as f32)).collect(),
        tokens,
        types,
        merges: Vec::new(),
        bos: 2,
        eos: 1,
    }
}

fn vocab_for(family: Family) -> Vocab {
    match family {
        Family::Llama => bpe_vocab(
            &[
                ("<|begin_of_text|>", 3),
                ("<|end_of_text|>", 3),
                ("<|start_header_id|>", 3),
                ("<|end_header_id|>", 3),
                ("<|eot_id|>", 3),
            ],
            "<|begin_of_text|>",
            "<|eot_id|>",
        ),
        Family::Qwen2 | Family::Qwen3 => bpe_vocab(
            &[
                ("<|endoftext|>", 3),
                ("<|im_start|>", 3),
                ("<|im_end|>", 3),
                ("<think>", 4),
                ("</think>", 4),
            ],
            "<|endoftext|>",
            "<|im_end|>",
        ),
        Family::Gemma3 => sp_vocab(),
    }
}

fn strs(v: &[String]) -> Value {
    Value::Array(v.iter().map(|s| Value::String(s.clone())).collect())
}

/// Writes a tiny random model of `family` to `path`. `with_template` stores the family's turn
/// format as `tokenizer.chat_template` (without it the labeler falls back to the same format).
pub fn write(
    family: Family,
    path: &Path,
    seed: u64,
    with_template: bool,
) -> Result<(), LabelerError> {
    let v = vocab_for(family);
    let arch = family.name();
    let head_dim = if family == Family::Gemma3 {
        GEMMA_HEAD_DIM
    } else {
        HEAD_DIM
    };
    let (heads, kv_heads) = if family == Family::Gemma3 {
        (2, 1)
    } else {
        (HEADS, KV_HEADS)
    };
    let u32v = |x: usize| Value::U32(x as u32);
    let mut md: Vec<(String, Value)> = vec![
        ("general.architecture".into(), Value::String(arch.into())),
        (
            "general.name".into(),
            Value::String(format!("tiny-random-{arch}")),
        ),
        (format!("{arch}.context_length"), u32v(2048)),
        (format!("{arch}.embedding_length"), u32v(HIDDEN)),
        (format!("{arch}.block_count"), u32v(LAYERS)),
        (format!("{arch}.feed_forward_length"), u32v(FFN)),
        (format!("{arch}.attention.head_count"), u32v(heads)),
        (format!("{arch}.attention.head_count_kv"), u32v(kv_heads)),
        (
            format!("{arch}.attention.layer_norm_rms_epsilon"),
            Value::F32(1e-6),
        ),
        (format!("{arch}.rope.freq_base"), Value::F32(10000.0)),
    ];
    match family {
        Family::Llama => md.push((format!("{arch}.rope.dimension_count"), u32v(head_dim))),
        Family::Qwen3 => md.push((format!("{arch}.attention.key_length"), u32v(head_dim))),
        Family::Gemma3 => {
            md.push((format!("{arch}.attention.key_length"), u32v(head_dim)));
            md.push((format!("{arch}.attention.value_length"), u32v(head_dim)));
            md.push((format!("{arch}.attention.sliding_window"), u32v(512)));
        }
        Family::Qwen2 => {}
    }
    let (model, pre) = match family {
        Family::Llama => ("gpt2", Some("llama-bpe")),
        Family::Qwen2 | Family::Qwen3 => ("gpt2", Some("qwen2")),
        Family::Gemma3 => ("llama", None),
    };
    md.push(("tokenizer.ggml.model".into(), Value::String(model.into())));
    if let Some(p) = pre {
        md.push(("tokenizer.ggml.pre".into(), Value::String(p.into())));
    }
    md.push(("tokenizer.ggml.tokens".into(), strs(&v.tokens)));
    md.push((
        "tokenizer.ggml.token_type".into(),
        Value::Array(v.types.iter().map(|&t| Value::I32(t)).collect()),
    ));
    if family == Family::Gemma3 {
        md.push((
            "tokenizer.ggml.scores".into(),
            Value::Array(v.scores.iter().map(|&s| Value::F32(s)).collect()),
        ));
        md.push(("tokenizer.ggml.add_space_prefix".into(), Value::Bool(false)));
    } else {
        md.push(("tokenizer.ggml.merges".into(), strs(&v.merges)));
    }
    md.push(("tokenizer.ggml.bos_token_id".into(), Value::U32(v.bos)));
    md.push(("tokenizer.ggml.eos_token_id".into(), Value::U32(v.eos)));
    // Llama 3 and Gemma templates write the BOS themselves; Qwen uses none.
    md.push(("tokenizer.ggml.add_bos_token".into(), Value::Bool(false)));
    if with_template {
        let tf = match family {
            Family::Llama => TemplateFamily::Llama3,
            Family::Qwen2 | Family::Qwen3 => TemplateFamily::ChatMl,
            Family::Gemma3 => TemplateFamily::Gemma,
        };
        md.push((
            "tokenizer.chat_template".into(),
            Value::String(fallback_template(tf).into()),
        ));
    }

    let mut rng = Rng(seed ^ (family as u64).wrapping_mul(0x1234_5678_9ABC_DEF1));
    let dev = Device::Cpu;
    let mut tensors: Vec<(String, QTensor)> = Vec::new();
    // GGUF dims are (cols, rows) in the file, candle shapes are (rows, cols): a weight that maps
    // `in` to `out` has candle shape (out, in).
    let mat = |name: String, out: usize, inp: usize, scale: f32, rng: &mut Rng| {
        let data: Vec<f32> = (0..out * inp).map(|_| rng.uniform(scale)).collect();
        (name, data, vec![out, inp])
    };
    let mut raw: Vec<(String, Vec<f32>, Vec<usize>)> = Vec::new();
    let vocab = v.tokens.len();
    raw.push(mat(
        "token_embd.weight".into(),
        vocab,
        HIDDEN,
        0.5,
        &mut rng,
    ));
    let norm = |name: String, n: usize, rng: &mut Rng| {
        let data: Vec<f32> = (0..n).map(|_| 1.0 + rng.uniform(0.1)).collect();
        (name, data, vec![n])
    };
    raw.push(norm("output_norm.weight".into(), HIDDEN, &mut rng));
    if family != Family::Gemma3 {
        raw.push(mat("output.weight".into(), vocab, HIDDEN, 0.5, &mut rng));
    }
    let wscale = 1.0 / (HIDDEN as f32).sqrt();
    for l in 0..LAYERS {
        let p = format!("blk.{l}");
        raw.push(norm(format!("{p}.attn_norm.weight"), HIDDEN, &mut rng));
        raw.push(mat(
            format!("{p}.attn_q.weight"),
            heads * head_dim,
            HIDDEN,
            wscale,
            &mut rng,
        ));
        raw.push(mat(
            format!("{p}.attn_k.weight"),
            kv_heads * head_dim,
            HIDDEN,
            wscale,
            &mut rng,
        ));
        raw.push(mat(
            format!("{p}.attn_v.weight"),
            kv_heads * head_dim,
            HIDDEN,
            wscale,
            &mut rng,
        ));
        raw.push(mat(
            format!("{p}.attn_output.weight"),
            HIDDEN,
            heads * head_dim,
            wscale,
            &mut rng,
        ));
        if family == Family::Qwen2 {
            for (n, d) in [
                ("q", heads * head_dim),
                ("k", kv_heads * head_dim),
                ("v", kv_heads * head_dim),
            ] {
                let data: Vec<f32> = (0..d).map(|_| rng.uniform(0.1)).collect();
                raw.push((format!("{p}.attn_{n}.bias"), data, vec![d]));
            }
        }
        if matches!(family, Family::Qwen3 | Family::Gemma3) {
            raw.push(norm(format!("{p}.attn_q_norm.weight"), head_dim, &mut rng));
            raw.push(norm(format!("{p}.attn_k_norm.weight"), head_dim, &mut rng));
        }
        if family == Family::Gemma3 {
            raw.push(norm(
                format!("{p}.post_attention_norm.weight"),
                HIDDEN,
                &mut rng,
            ));
            raw.push(norm(format!("{p}.post_ffw_norm.weight"), HIDDEN, &mut rng));
        }
        raw.push(norm(format!("{p}.ffn_norm.weight"), HIDDEN, &mut rng));
        raw.push(mat(
            format!("{p}.ffn_gate.weight"),
            FFN,
            HIDDEN,
            wscale,
            &mut rng,
        ));
        raw.push(mat(
            format!("{p}.ffn_up.weight"),
            FFN,
            HIDDEN,
            wscale,
            &mut rng,
        ));
        raw.push(mat(
            format!("{p}.ffn_down.weight"),
            HIDDEN,
            FFN,
            1.0 / (FFN as f32).sqrt(),
            &mut rng,
        ));
    }
    for (name, data, shape) in raw {
        let t = Tensor::from_vec(data, shape, &dev)?;
        tensors.push((name, QTensor::quantize(&t, GgmlDType::F32)?));
    }
    let md_refs: Vec<(&str, &Value)> = md.iter().map(|(k, v)| (k.as_str(), v)).collect();
    let t_refs: Vec<(&str, &QTensor)> = tensors.iter().map(|(k, v)| (k.as_str(), v)).collect();
    let mut f = std::io::BufWriter::new(std::fs::File::create(path)?);
    gguf_file::write(&mut f, &md_refs, &t_refs)?;
    use std::io::Write;
    f.flush()?;
    Ok(())
}

/// FNV-1a over a file, the fingerprint that ties a reference output to the exact file it was
/// computed on (the reference script computes the same).
pub fn fingerprint(path: &Path) -> Result<String, LabelerError> {
    let bytes = std::fs::read(path)?;
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    for b in bytes {
        h ^= u64::from(b);
        h = h.wrapping_mul(0x0000_0100_0000_01b3);
    }
    Ok(format!("{h:016x}"))
}
