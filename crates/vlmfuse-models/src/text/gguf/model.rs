//! The quantized decoder families candle runs from a GGUF file, behind one small interface:
//! feed tokens at a position, get the next-token logits.
//!
//! Llama, Qwen2 and Qwen3 run candle-transformers' models; Gemma 3 runs this crate's own
//! decoder (`llm::gemma3`, which says why).
//!
//! Why a prefix snapshot for some families only: every answer shares the long system prompt,
//! so its key/value cache can be computed once and reused. That needs a model whose state can be
//! cloned (qwen2's `ModelWeights` in candle 0.11.1 is not `Clone`) and a correct causal mask for
//! a multi-token chunk fed after a cache. Qwen2 prefills the whole prompt per answer, which is
//! correct, only slower.

use super::gemma3::Gemma3;
use crate::ModelError;
use candle_core::quantized::gguf_file::Content;
use candle_core::{Device, Tensor};
use candle_transformers::models::{quantized_llama, quantized_qwen2, quantized_qwen3};
use std::io::{Read, Seek};

/// The decoder families the GGUF labeler runs, from `general.architecture`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Family {
    /// `llama`: Llama 3.x (and other llama-architecture files).
    Llama,
    Qwen2,
    Qwen3,
    Gemma3,
}

impl Family {
    pub fn from_architecture(arch: &str) -> Result<Self, ModelError> {
        match arch {
            "llama" => Ok(Family::Llama),
            "qwen2" => Ok(Family::Qwen2),
            "qwen3" => Ok(Family::Qwen3),
            "gemma3" => Ok(Family::Gemma3),
            other => Err(ModelError::BadConfig(format!(
                "unsupported GGUF architecture {other:?} (supported: llama, qwen2, qwen3, gemma3)"
            ))),
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            Family::Llama => "llama",
            Family::Qwen2 => "qwen2",
            Family::Qwen3 => "qwen3",
            Family::Gemma3 => "gemma3",
        }
    }

    /// Whether a cached prefix can be cloned and continued with a multi-token chunk.
    pub fn reuses_prefix(self) -> bool {
        matches!(self, Family::Llama | Family::Qwen3 | Family::Gemma3)
    }
}

enum Weights {
    Llama(quantized_llama::ModelWeights),
    Qwen2(quantized_qwen2::ModelWeights),
    Qwen3(quantized_qwen3::ModelWeights),
    Gemma3(Gemma3),
}

/// A loaded model with its key/value cache.
pub struct Decoder {
    family: Family,
    w: Weights,
    device: Device,
    /// Tokens in the cache.
    pos: usize,
}

impl Decoder {
    pub fn load<R: Read + Seek>(
        ct: Content,
        reader: &mut R,
        device: &Device,
    ) -> Result<Self, ModelError> {
        let arch = ct
            .metadata
            .get("general.architecture")
            .and_then(|v| v.to_string().ok())
            .cloned()
            .ok_or_else(|| ModelError::BadConfig("GGUF has no general.architecture".into()))?;
        let family = Family::from_architecture(&arch)?;
        let w = match family {
            Family::Llama => Weights::Llama(quantized_llama::ModelWeights::from_gguf(
                ct, reader, device,
            )?),
            Family::Qwen2 => Weights::Qwen2(quantized_qwen2::ModelWeights::from_gguf(
                ct, reader, device,
            )?),
            Family::Qwen3 => Weights::Qwen3(quantized_qwen3::ModelWeights::from_gguf(
                ct, reader, device,
            )?),
            Family::Gemma3 => Weights::Gemma3(Gemma3::from_gguf(&ct, reader, device)?),
        };
        Ok(Self {
            family,
            w,
            device: device.clone(),
            pos: 0,
        })
    }

    pub fn family(&self) -> Family {
        self.family
    }

    /// Tokens currently in the cache.
    pub fn pos(&self) -> usize {
        self.pos
    }

    /// Empties the cache (the next [`Decoder::feed`] starts at position 0).
    pub fn reset(&mut self) {
        match &mut self.w {
            Weights::Llama(m) => m.clear_kv_cache(),
            Weights::Qwen2(m) => m.clear_kv_cache(),
            Weights::Qwen3(m) => m.clear_kv_cache(),
            Weights::Gemma3(m) => m.clear_kv_cache(),
        }
        self.pos = 0;
    }

    /// A copy sharing the weights and the current cache, for the families that allow it.
    pub fn snapshot(&self) -> Option<Self> {
        let w = match &self.w {
            Weights::Llama(m) if self.family.reuses_prefix() => Weights::Llama(m.clone()),
            Weights::Qwen3(m) if self.family.reuses_prefix() => Weights::Qwen3(m.clone()),
            Weights::Gemma3(m) if self.family.reuses_prefix() => Weights::Gemma3(m.clone()),
            _ => return None,
        };
        Some(Self {
            family: self.family,
            w,
            device: self.device.clone(),
            pos: self.pos,
        })
    }

    /// Feeds `ids` after the cached tokens and returns the logits for the next token.
    pub fn feed(&mut self, ids: &[u32]) -> Result<Vec<f32>, ModelError> {
        if ids.is_empty() {
            return Err(ModelError::InvalidInput(
                "feed called with no tokens".into(),
            ));
        }
        let x = Tensor::new(ids, &self.device)?.unsqueeze(0)?;
        let logits = match &mut self.w {
            Weights::Llama(m) => m.forward(&x, self.pos)?,
            Weights::Qwen2(m) => m.forward(&x, self.pos)?,
            Weights::Qwen3(m) => m.forward(&x, self.pos)?,
            Weights::Gemma3(m) => m.forward(&x, self.pos)?,
        };
        self.pos += ids.len();
        Ok(logits
            .flatten_all()?
            .to_dtype(candle_core::DType::F32)?
            .to_vec1()?)
    }
}
