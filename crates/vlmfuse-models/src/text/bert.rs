//! The candle engine behind [`SentenceEncoder`]: a BERT sentence encoder (all-MiniLM-L6-v2) with
//! mean pooling, loaded from a `model.safetensors` / `tokenizer.json` / `config.json` directory.
//!
//! Why length buckets inside one call: the matcher sends every clause of every answer of a round
//! at once, and clauses range from two words to thirty. One padded batch would pay for the
//! longest clause in every row; sorting by length and running a few buckets costs a few extra
//! forward calls (well under a millisecond each) and saves most of the padded compute. The
//! caller still makes one call, and the result is identical to per-text encoding up to float
//! rounding (padding is masked out of attention and pooling).

use super::encoder::length_groups;
use super::SentenceEncoder;
use crate::ModelError;
use candle_core::{DType, Device, Tensor};
use candle_nn::VarBuilder;
use candle_transformers::models::bert::{BertModel, Config as BertConfig};
use std::path::Path;
use tokenizers::{Tokenizer, TruncationParams};

/// Tokens per text; clauses are short, and a runaway "clause" (a paragraph without punctuation)
/// must not make the whole batch quadratic.
pub const MAX_TOKENS: usize = 128;

/// A padded token costs the same as a real one; a forward call costs about this many tokens of
/// fixed overhead (measured: ~0.3 ms per call for MiniLM on 2 cores, ~1 µs per token-layer).
const CALL_OVERHEAD_TOKENS: usize = 48;

pub struct CandleEncoder {
    model: BertModel,
    tokenizer: Tokenizer,
    device: Device,
    dim: usize,
}

impl CandleEncoder {
    /// Loads the three files of a sentence-transformers BERT export (blocking).
    pub fn load(model_dir: &Path) -> Result<Self, ModelError> {
        let device = Device::Cpu;
        let f = |n: &str| {
            let p = model_dir.join(n);
            if p.is_file() {
                Ok(p)
            } else {
                Err(ModelError::MissingWeights {
                    file: n.to_string(),
                    searched: vec![model_dir.to_path_buf()],
                })
            }
        };
        let (weights, tok_path, conf_path) = (
            f("model.safetensors")?,
            f("tokenizer.json")?,
            f("config.json")?,
        );
        let text = std::fs::read_to_string(&conf_path).map_err(|e| ModelError::Io {
            path: conf_path.clone(),
            source: e,
        })?;
        let config: BertConfig =
            serde_json::from_str(&text).map_err(|e| ModelError::BadWeights {
                path: conf_path.clone(),
                reason: e.to_string(),
            })?;
        // SAFETY: the file is memory-mapped read-only; it must not be modified while loaded,
        // which holds for the asset cache.
        let vb = unsafe { VarBuilder::from_mmaped_safetensors(&[weights], DType::F32, &device)? };
        let model = BertModel::load(vb, &config)?;
        let mut tokenizer =
            Tokenizer::from_file(tok_path).map_err(|e| ModelError::Tokenizer(e.to_string()))?;
        // Padding is done here per bucket, not by the tokenizer over the whole batch.
        tokenizer.with_padding(None);
        tokenizer
            .with_truncation(Some(TruncationParams {
                max_length: MAX_TOKENS,
                ..Default::default()
            }))
            .map_err(|e| ModelError::Tokenizer(e.to_string()))?;
        Ok(Self {
            model,
            tokenizer,
            device,
            dim: config.hidden_size,
        })
    }

    /// Mean-pooled, unit-L2 embeddings of equally padded rows, shape (n, dim).
    fn forward(&self, rows: &[&[u32]]) -> Result<Tensor, ModelError> {
        let len = rows.iter().map(|r| r.len()).max().unwrap_or(0).max(1);
        let n = rows.len();
        let mut ids = vec![0u32; n * len];
        let mut mask = vec![0u32; n * len];
        for (i, r) in rows.iter().enumerate() {
            ids[i * len..i * len + r.len()].copy_from_slice(r);
            mask[i * len..i * len + r.len()].fill(1);
        }
        let ids = Tensor::from_vec(ids, (n, len), &self.device)?;
        let mask = Tensor::from_vec(mask, (n, len), &self.device)?;
        let type_ids = ids.zeros_like()?;
        let hidden = self.model.forward(&ids, &type_ids, Some(&mask))?;
        let m = mask.to_dtype(DType::F32)?.unsqueeze(2)?;
        let summed = hidden.broadcast_mul(&m)?.sum(1)?;
        let counts = m.sum(1)?.clamp(1e-9, f64::MAX)?;
        let mean = summed.broadcast_div(&counts)?;
        let norm = mean.sqr()?.sum_keepdim(1)?.sqrt()?.clamp(1e-12, f64::MAX)?;
        Ok(mean.broadcast_div(&norm)?)
    }
}

impl SentenceEncoder for CandleEncoder {
    fn engine(&self) -> &str {
        "candle"
    }

    fn dim(&self) -> usize {
        self.dim
    }

    fn encode(&self, texts: &[&str]) -> Result<Vec<Vec<f32>>, ModelError> {
        if texts.is_empty() {
            return Ok(Vec::new());
        }
        let enc = self
            .tokenizer
            .encode_batch(texts.to_vec(), true)
            .map_err(|e| ModelError::Tokenizer(e.to_string()))?;
        let lens: Vec<usize> = enc.iter().map(|e| e.get_ids().len()).collect();
        let mut out = vec![Vec::new(); texts.len()];
        for group in length_groups(&lens, CALL_OVERHEAD_TOKENS) {
            let rows: Vec<&[u32]> = group.iter().map(|&i| enc[i].get_ids()).collect();
            let emb: Vec<Vec<f32>> = self.forward(&rows)?.to_vec2()?;
            for (&i, e) in group.iter().zip(emb) {
                out[i] = e;
            }
        }
        Ok(out)
    }
}
