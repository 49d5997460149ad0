//! What the LLaMA-family VLMs (VideoLLaVA, VideoLLaMA2, VLAAD) share around their language
//! model: left-padded batches, the input view, splicing a clip's tokens into the prompt's
//! embeddings, one decoding step, and loading a checkpoint with a LoRA adapter merged.

use std::collections::HashMap;
use std::path::PathBuf;

use candle_core::{DType, Device, Tensor};
use candle_nn::VarBuilder;

use crate::lora::{load_adapter, merge_adapter_mapped};
use crate::models::family::InputView;
use crate::models::video_llava::processor::EncodedBatch;
use crate::models::video_llava::text::{KvCache, LlamaText};
use crate::weights::{var_builder, WeightSource};
use crate::ModelError;

/// How to load a checkpoint of a family without options of its own (Qwen3-VL, VideoLLaMA2,
/// VLAAD).
#[derive(Debug, Clone)]
pub struct LoadOptions {
    pub dtype: DType,
    pub device: Device,
    /// A PEFT LoRA adapter merged into the weights at load.
    pub adapter: Option<WeightSource>,
}

impl Default for LoadOptions {
    fn default() -> Self {
        Self {
            dtype: DType::F32,
            device: Device::Cpu,
            adapter: None,
        }
    }
}

/// Text of `ids` (special tokens dropped when `skip_special`).
pub fn decode(
    tok: &tokenizers::Tokenizer,
    ids: &[u32],
    skip_special: bool,
) -> Result<String, ModelError> {
    tok.decode(ids, skip_special)
        .map_err(|e| ModelError::InvalidInput(format!("tokenizer: {e}")))
}

/// The id that stands for one visual token in a prompt row (the repositories use one marker
/// for the whole clip, `-201` or `<ImageHere>`; here each of the clip's tokens has a position
/// of its own, so the rows are the LLM's real input length).
pub const VISUAL_TOKEN: u32 = u32::MAX;

/// Left-pads rows to one length with `pad` (generation needs every row's last token at the
/// same index); the mask marks the real tokens.
pub fn pad_left(rows: Vec<Vec<u32>>, pad: u32) -> EncodedBatch {
    let len = rows.iter().map(|r| r.len()).max().unwrap_or(0);
    let mut input_ids = Vec::with_capacity(rows.len());
    let mut attention_mask = Vec::with_capacity(rows.len());
    for r in rows {
        let n = len - r.len();
        let mut ids = vec![pad; n];
        ids.extend_from_slice(&r);
        let mut m = vec![false; n];
        m.extend(std::iter::repeat_n(true, r.len()));
        input_ids.push(ids);
        attention_mask.push(m);
    }
    EncodedBatch {
        input_ids,
        attention_mask,
    }
}

/// The [`InputView`] of a batch whose visual positions hold `visual`.
pub fn view(ids: &EncodedBatch, visual: u32) -> InputView {
    InputView {
        input_ids: ids.input_ids.clone(),
        visual_tokens: ids
            .input_ids
            .iter()
            .map(|r| r.iter().filter(|&&t| t == visual).count())
            .collect(),
        prompt_tokens: ids
            .attention_mask
            .iter()
            .map(|m| m.iter().filter(|&&m| m).count())
            .collect(),
    }
}

/// Token embeddings of `ids` with the [`VISUAL_TOKEN`] positions replaced, in order, by the
/// rows of `features()` (`[Σ visual tokens, hidden]`, computed only when there are any).
pub fn splice_visual(
    text: &LlamaText,
    ids: &EncodedBatch,
    features: impl FnOnce() -> Result<Tensor, ModelError>,
) -> Result<Tensor, ModelError> {
    let (b, t) = (ids.batch(), ids.seq_len());
    if b == 0 || t == 0 {
        return Err(ModelError::InvalidInput("an empty prompt".into()));
    }
    let cfg = text.config();
    let (vocab, hid) = (cfg.vocab_size as u32, cfg.hidden_size);
    let flat: Vec<u32> = ids.input_ids.iter().flatten().copied().collect();
    if let Some(bad) = flat.iter().find(|&&i| i >= vocab && i != VISUAL_TOKEN) {
        return Err(ModelError::InvalidInput(format!(
            "token id {bad} is outside the vocabulary ({vocab})"
        )));
    }
    let text_ids: Vec<u32> = flat
        .iter()
        .map(|&i| if i == VISUAL_TOKEN { 0 } else { i })
        .collect();
    let emb = text
        .embed(&Tensor::from_vec(text_ids, (b, t), text.device())?)?
        .reshape((b * t, hid))?;
    let nv = flat.iter().filter(|&&i| i == VISUAL_TOKEN).count();
    if nv == 0 {
        return Ok(emb.reshape((b, t, hid))?);
    }
    let f = features()?.to_dtype(text.dtype())?;
    if f.dim(0)? != nv {
        return Err(ModelError::InvalidInput(format!(
            "clip tokens and visual positions do not match: {nv} positions, {} tokens",
            f.dim(0)?
        )));
    }
    let mut k = 0usize;
    let src: Vec<u32> = flat
        .iter()
        .enumerate()
        .map(|(p, &id)| {
            if id == VISUAL_TOKEN {
                k += 1;
                (b * t + k - 1) as u32
            } else {
                p as u32
            }
        })
        .collect();
    let table = Tensor::cat(&[emb, f], 0)?;
    let src = Tensor::from_vec(src, b * t, text.device())?;
    Ok(table.index_select(&src, 0)?.reshape((b, t, hid))?)
}

/// Feeds one token per row after a prefill and returns the next logits, `[batch, vocab]`.
pub fn step(text: &LlamaText, tokens: &[u32], cache: &mut KvCache) -> Result<Tensor, ModelError> {
    if cache.is_empty() {
        return Err(ModelError::InvalidInput("step before prefill".into()));
    }
    if tokens.len() != cache.batch() {
        return Err(ModelError::InvalidInput(format!(
            "{} tokens for a batch of {}",
            tokens.len(),
            cache.batch()
        )));
    }
    let ids = Tensor::from_vec(tokens.to_vec(), (tokens.len(), 1), text.device())?;
    let emb = text.embed(&ids)?;
    let valid = vec![vec![true]; tokens.len()];
    Ok(text.forward(&emb, &valid, cache)?)
}

/// Safetensors shards as one [`VarBuilder`]: memory-mapped when there is no adapter; else read
/// into memory (renamed by `map`, so an adapter of either naming finds its weights), `extra`
/// tensors laid over them, the adapter merged, and moved to `device` in `dtype`. Returns the
/// merged keys too.
pub fn load_merged(
    files: &[PathBuf],
    adapter: Option<&WeightSource>,
    extra: HashMap<String, Tensor>,
    map: impl Fn(&str) -> String + Copy,
    dtype: DType,
    device: &Device,
) -> Result<(VarBuilder<'static>, Vec<String>), ModelError> {
    let Some(adapter) = adapter else {
        return Ok((var_builder(files, dtype, device)?, Vec::new()));
    };
    let mut base = HashMap::new();
    for f in files {
        let t = candle_core::safetensors::load(f, &Device::Cpu).map_err(|e| {
            ModelError::BadWeights {
                path: f.clone(),
                reason: e.to_string(),
            }
        })?;
        base.extend(t.into_iter().map(|(k, v)| (map(&k), v)));
    }
    base.extend(extra);
    let (lcfg, lt) = load_adapter(adapter)?;
    let merged = merge_adapter_mapped(&mut base, &lt, &lcfg, map).map_err(|e| match e {
        ModelError::BadWeights { reason, .. } => ModelError::BadWeights {
            path: adapter
                .resolve_optional("adapter_model.safetensors")
                .ok()
                .flatten()
                .unwrap_or_else(|| PathBuf::from(adapter.describe())),
            reason,
        },
        other => other,
    })?;
    tracing::info!(adapter = %adapter.describe(), modules = merged.len(), "merged LoRA adapter");
    let base = base
        .into_iter()
        .map(|(k, t)| {
            let t = if t.dtype().is_float() {
                t.to_dtype(dtype)?
            } else {
                t
            };
            Ok((k, t.to_device(device)?))
        })
        .collect::<Result<HashMap<_, _>, candle_core::Error>>()?;
    Ok((VarBuilder::from_tensors(base, dtype, device), merged))
}
