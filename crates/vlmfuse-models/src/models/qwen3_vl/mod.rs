//! Qwen3-VL (`Qwen3VLForConditionalGeneration`) written to compute what transformers computes,
//! for video clips.
//!
//! candle-transformers 0.11.1 ships a `qwen3_vl` that differs from the reference in ways that
//! move first-token logits by 5% of their range on an 8-frame clip: 1-D positions instead of
//! M-RoPE, no causal mask inside a multi-token chunk, the tanh GELU in the patch merger, and a KV
//! cache that cannot be reset (so its callers rebuild the model per request and prefill token by
//! token). This module owns the model instead; it reuses candle-nn's layers and follows
//! candle-transformers' file layout (`config`, `vision`, `text`) plus the `processor`.
//!
//! Use: load once with [`Qwen3Vl::load`], then per request [`Qwen3Vl::prefill`] a batch of
//! [`Sequence`]s (built by [`Qwen3VlProcessor`]) into a [`Cache`], and [`Qwen3Vl::step`] one
//! token per row at a time. The model is immutable (`&self`): all request state lives in the
//! cache, so one loaded model serves every request and `prefill` starts each one afresh.

pub mod config;
mod family;
pub mod processor;
pub mod text;
pub mod vision;

use std::collections::HashMap;

use candle_core::{DType, Device, Tensor};
use candle_nn::kv_cache::KvCache;
use candle_nn::VarBuilder;

pub use config::{Config, TextConfig, VisionConfig};
pub use family::Qwen3VlFamily;
pub use processor::{
    smart_resize, ProcessedVideo, Qwen3VlProcessor, VideoProcessor, VideoProcessorConfig,
};

use crate::lora::{load_adapter, merge_adapter};
use crate::weights::{var_builder, WeightSource};
use crate::ModelError;

/// Above this many f32 attention scores per call, the vision tower splits its heads into
/// chunks: a 1280x720 frame has 3,600 patches, and 16 heads of 3,600² scores would be 830 MB.
const ATTN_CHUNK_ELEMS: usize = 1 << 26;

/// Scaled dot-product attention `[B, H, L, d] x [B, H, S, d]`, scores and softmax in f32 (as
/// the reference's `softmax(dtype=float32)`), optional additive mask broadcast over `[B, H, L, S]`.
pub(crate) fn attention(
    q: &Tensor,
    k: &Tensor,
    v: &Tensor,
    scale: f64,
    mask: Option<&Tensor>,
) -> candle_core::Result<Tensor> {
    let (b, h, l, _) = q.dims4()?;
    let s = k.dim(2)?;
    let per_head = b * l * s;
    if h > 1 && per_head * h > ATTN_CHUNK_ELEMS && mask.is_none() {
        let step = (ATTN_CHUNK_ELEMS / per_head).max(1);
        let mut outs = Vec::new();
        let mut start = 0;
        while start < h {
            let n = step.min(h - start);
            outs.push(attention(
                &q.narrow(1, start, n)?.contiguous()?,
                &k.narrow(1, start, n)?.contiguous()?,
                &v.narrow(1, start, n)?.contiguous()?,
                scale,
                None,
            )?);
            start += n;
        }
        return Tensor::cat(&outs, 1);
    }
    let dt = q.dtype();
    let att = (q.matmul(&k.t()?)? * scale)?.to_dtype(DType::F32)?;
    let att = match mask {
        Some(m) => att.broadcast_add(m)?,
        None => att,
    };
    let att = crate::ops::softmax_last_dim(&att)?.to_dtype(dt)?;
    att.matmul(&v.contiguous()?)
}

/// Attention for grouped-query heads: `q` is `[B, kv_heads, rep * L, d]` (the `rep` query heads
/// of each key/value head stacked), `k`/`v` `[B, kv_heads, S, d]`, `mask` `[B, 1, L, S]`.
pub(crate) fn attention_grouped(
    q: &Tensor,
    k: &Tensor,
    v: &Tensor,
    scale: f64,
    mask: Option<&Tensor>,
    rep: usize,
) -> candle_core::Result<Tensor> {
    let (b, nkv, rl, _) = q.dims4()?;
    let s = k.dim(2)?;
    let l = rl / rep;
    let dt = q.dtype();
    let att = (q.matmul(&k.t()?)? * scale)?.to_dtype(DType::F32)?;
    let att = match mask {
        Some(m) => att
            .reshape((b, nkv * rep, l, s))?
            .broadcast_add(m)?
            .reshape((b, nkv, rl, s))?,
        None => att,
    };
    let att = crate::ops::softmax_last_dim(&att)?.to_dtype(dt)?;
    att.matmul(v)
}

/// A video ready for the vision tower: patch rows in processor order and its grid.
#[derive(Debug, Clone, PartialEq)]
pub struct VideoInput {
    /// Row-major `[t * h * w, channels * temporal_patch * patch²]`.
    pub pixel_values: Vec<f32>,
    /// `[t, h, w]` in patches (not merged), as `video_grid_thw`.
    pub grid_thw: [usize; 3],
}

/// One row of a batch: the prompt's token ids (placeholders included) and its video.
#[derive(Debug, Clone, PartialEq)]
pub struct Sequence {
    pub ids: Vec<u32>,
    pub video: Option<VideoInput>,
}

/// Per-request state: the KV cache of every layer, each row's next M-RoPE position and left
/// padding. [`Qwen3Vl::prefill`] resets it.
pub struct Cache {
    kv: Vec<KvCache>,
    next_pos: Vec<i64>,
    pad: Vec<usize>,
    len: usize,
    capacity: usize,
}

impl Cache {
    /// `capacity`: tokens to reserve per row (prompt + expected new tokens); it grows past that
    /// if needed, at the cost of a copy.
    pub fn new(capacity: usize) -> Self {
        Self {
            kv: Vec::new(),
            next_pos: Vec::new(),
            pad: Vec::new(),
            len: 0,
            capacity: capacity.max(1),
        }
    }

    pub fn reset(&mut self) {
        self.kv.clear();
        self.next_pos.clear();
        self.pad.clear();
        self.len = 0;
    }

    /// Rows of the batch in flight (0 before the first prefill).
    pub fn batch_size(&self) -> usize {
        self.next_pos.len()
    }

    /// Tokens per row in the cache, padding included.
    pub fn len(&self) -> usize {
        self.len
    }

    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// Left padding of each row.
    pub fn padding(&self) -> &[usize] {
        &self.pad
    }

    /// The M-RoPE position the next token of each row gets.
    pub fn next_positions(&self) -> &[i64] {
        &self.next_pos
    }
}

/// How to load a checkpoint: the options every family without its own take.
pub use crate::models::common::LoadOptions;

/// M-RoPE positions of one prompt (`get_rope_index` of the reference): text tokens count up on
/// all three rows; each run of visual placeholders is one frame of `grids` (`[t, h, w]` in
/// patches, split into `t` single-frame grids) laid out as (start, start + row, start + col) in
/// merged-token units, after which text resumes at `start + max(rows, cols)`. Returns the rows
/// and the position of the next token.
pub fn rope_index(
    ids: &[u32],
    video_token_id: u32,
    grids: &[[usize; 3]],
    merge: usize,
) -> Result<([Vec<i64>; 3], i64), ModelError> {
    let mut frames = grids
        .iter()
        .flat_map(|g| std::iter::repeat_n([1, g[1], g[2]], g[0]));
    let mut pos: [Vec<i64>; 3] = Default::default();
    let mut cur: i64 = 0;
    let mut i = 0;
    while i < ids.len() {
        if ids[i] != video_token_id {
            for p in pos.iter_mut() {
                p.push(cur);
            }
            cur += 1;
            i += 1;
            continue;
        }
        let run = ids[i..]
            .iter()
            .take_while(|&&t| t == video_token_id)
            .count();
        let [_, h, w] = frames.next().ok_or_else(|| {
            ModelError::InvalidInput(format!(
                "a run of {run} video placeholders at token {i} has no frame left in the video"
            ))
        })?;
        let (lh, lw) = (h / merge, w / merge);
        if run != lh * lw {
            return Err(ModelError::InvalidInput(format!(
                "a run of {run} video placeholders at token {i}, but the frame has {lh}x{lw} = {} \
                 merged tokens",
                lh * lw
            )));
        }
        for r in 0..lh {
            for c in 0..lw {
                pos[0].push(cur);
                pos[1].push(cur + r as i64);
                pos[2].push(cur + c as i64);
            }
        }
        cur += lh.max(lw) as i64;
        i += run;
    }
    if frames.next().is_some() {
        return Err(ModelError::InvalidInput(
            "the video has more frames than the prompt has placeholder runs".into(),
        ));
    }
    Ok((pos, cur))
}

/// A loaded Qwen3-VL.
pub struct Qwen3Vl {
    config: Config,
    vision: vision::VisionModel,
    text: text::TextModel,
    device: Device,
    dtype: DType,
    merged_lora: Vec<String>,
}

fn weights_err(src: &WeightSource) -> impl Fn(candle_core::Error) -> ModelError + '_ {
    move |e| ModelError::BadWeights {
        path: src.describe().into(),
        reason: e.to_string(),
    }
}

impl Qwen3Vl {
    /// Builds the model from a [`VarBuilder`] rooted at the checkpoint's top level.
    pub fn new(config: Config, vb: VarBuilder) -> candle_core::Result<Self> {
        let vision = vision::VisionModel::new(&config.vision, vb.pp("model.visual"))?;
        let text = text::TextModel::new(&config.text, config.tie_word_embeddings, vb.clone())?;
        Ok(Self {
            config,
            vision,
            text,
            device: vb.device().clone(),
            dtype: vb.dtype(),
            merged_lora: Vec::new(),
        })
    }

    /// Reads `config.json` and the safetensors (memory-mapped; copied only when an adapter is
    /// merged). Blocking and slow for real checkpoints: once at startup.
    pub fn load(weights: &WeightSource, opts: &LoadOptions) -> Result<Self, ModelError> {
        let raw: serde_json::Value = weights.read_json("config.json")?;
        let config = Config::from_json(&raw)?;
        let files = weights.safetensors_files()?;
        let Some(adapter) = &opts.adapter else {
            let vb = var_builder(&files, opts.dtype, &opts.device)?;
            return Self::new(config, vb).map_err(weights_err(weights));
        };
        let mut tensors = HashMap::new();
        for f in &files {
            let t = candle_core::safetensors::load(f, &Device::Cpu).map_err(|e| {
                ModelError::BadWeights {
                    path: f.clone(),
                    reason: e.to_string(),
                }
            })?;
            tensors.extend(t);
        }
        let (lcfg, lt) = load_adapter(adapter)?;
        let merged = merge_adapter(&mut tensors, &lt, &lcfg).map_err(|e| match e {
            ModelError::BadWeights { reason, .. } => ModelError::BadWeights {
                path: adapter
                    .resolve("adapter_model.safetensors")
                    .unwrap_or_default(),
                reason,
            },
            other => other,
        })?;
        let vb = VarBuilder::from_tensors(tensors, opts.dtype, &opts.device);
        let mut m = Self::new(config, vb).map_err(weights_err(weights))?;
        m.merged_lora = merged;
        Ok(m)
    }

    pub fn config(&self) -> &Config {
        &self.config
    }

    pub fn device(&self) -> &Device {
        &self.device
    }

    pub fn dtype(&self) -> DType {
        self.dtype
    }

    /// Base weight keys a LoRA adapter changed at load.
    pub fn merged_lora_keys(&self) -> &[String] {
        &self.merged_lora
    }

    /// Checks one row before any tensor work, so a malformed request is a clear error rather
    /// than an index panic or a shape error deep inside candle.
    fn check(&self, i: usize, seq: &Sequence) -> Result<Vec<[usize; 3]>, ModelError> {
        let c = &self.config;
        let bad = |m: String| ModelError::InvalidInput(format!("batch row {i}: {m}"));
        if seq.ids.is_empty() {
            return Err(bad("no tokens".into()));
        }
        if let Some(&t) = seq.ids.iter().find(|&&t| t as usize >= c.text.vocab_size) {
            return Err(bad(format!(
                "token id {t} is outside the vocabulary ({})",
                c.text.vocab_size
            )));
        }
        if seq.ids.contains(&c.image_token_id) {
            return Err(bad(
                "image placeholders are not supported; send frames as a video".into(),
            ));
        }
        let pads = seq.ids.iter().filter(|&&t| t == c.video_token_id).count();
        let m = c.vision.spatial_merge_size;
        match &seq.video {
            None if pads > 0 => Err(bad(format!("{pads} video placeholders but no video"))),
            None => Ok(Vec::new()),
            Some(v) => {
                let [t, h, w] = v.grid_thw;
                if t == 0 || h == 0 || w == 0 || h % m != 0 || w % m != 0 {
                    return Err(bad(format!(
                        "video grid {:?} must be positive with height and width multiples of {m}",
                        v.grid_thw
                    )));
                }
                let rows = t * h * w;
                if v.pixel_values.len() != rows * c.vision.patch_dim() {
                    return Err(bad(format!(
                        "{} pixel values for a {:?} grid of {}-value patches",
                        v.pixel_values.len(),
                        v.grid_thw,
                        c.vision.patch_dim()
                    )));
                }
                if pads != rows / (m * m) {
                    return Err(bad(format!(
                        "{pads} video placeholders for {} merged video tokens",
                        rows / (m * m)
                    )));
                }
                Ok(vec![v.grid_thw])
            }
        }
    }

    /// Runs the prompts of a batch in one forward pass (vision tower for every video, then the
    /// decoder over all tokens with a causal mask) and returns each row's next-token logits
    /// (`[batch, vocab]`, f32). Rows of different lengths are left-padded and masked, so each
    /// row computes what it would alone. `cache` is reset first.
    pub fn prefill(&self, batch: &[Sequence], cache: &mut Cache) -> Result<Tensor, ModelError> {
        if batch.is_empty() {
            return Err(ModelError::InvalidInput("empty batch".into()));
        }
        let c = &self.config;
        let merge = c.vision.spatial_merge_size;
        let b = batch.len();
        let l = batch.iter().map(|s| s.ids.len()).max().unwrap_or(0);
        let mut grids = Vec::new();
        let mut pixels = Vec::new();
        let mut pos: [Vec<i64>; 3] = Default::default();
        let mut ids = Vec::with_capacity(b * l);
        let mut visual_rows = Vec::new();
        cache.reset();
        for (i, seq) in batch.iter().enumerate() {
            let g = self.check(i, seq)?;
            let (p, next) = rope_index(&seq.ids, c.video_token_id, &g, merge)?;
            let pad = l - seq.ids.len();
            for (axis, row) in p.into_iter().enumerate() {
                pos[axis].extend(std::iter::repeat_n(0, pad));
                pos[axis].extend(row);
            }
            // Pad with the row's own first token: any valid id works, since masked keys get zero
            // weight and padded queries are never read.
            ids.extend(std::iter::repeat_n(seq.ids[0], pad));
            ids.extend_from_slice(&seq.ids);
            for (j, &t) in seq.ids.iter().enumerate() {
                if t == c.video_token_id {
                    visual_rows.push((i * l + pad + j) as u32);
                }
            }
            if let Some(v) = &seq.video {
                pixels.push(Tensor::from_slice(
                    &v.pixel_values,
                    (
                        v.pixel_values.len() / c.vision.patch_dim(),
                        c.vision.patch_dim(),
                    ),
                    &self.device,
                )?);
            }
            grids.extend(g);
            cache.next_pos.push(next);
            cache.pad.push(pad);
        }

        let ids_t = Tensor::from_vec(ids, (b, l), &self.device)?;
        let mut embeds = self.text.embed(&ids_t)?;
        let hidden = embeds.dim(2)?;
        let mut deep = None;
        if !grids.is_empty() {
            let out = self.vision.forward(&Tensor::cat(&pixels, 0)?, &grids)?;
            // Placeholders take the visual rows in order: gather from [token rows; visual rows].
            let n = b * l;
            let mut gather: Vec<u32> = (0..n as u32).collect();
            for (k, &r) in visual_rows.iter().enumerate() {
                gather[r as usize] = (n + k) as u32;
            }
            let table = Tensor::cat(
                &[
                    embeds.reshape((n, hidden))?,
                    out.embeds.to_dtype(embeds.dtype())?,
                ],
                0,
            )?;
            embeds = table
                .index_select(&Tensor::from_vec(gather, n, &self.device)?, 0)?
                .reshape((b, l, hidden))?;
            deep = Some((
                Tensor::from_vec(visual_rows, visual_tokens(&grids, merge), &self.device)?,
                out.deepstack,
            ));
        }

        let rope = self.text.rope(&pos, b, l)?;
        let mask = self.mask(&cache.pad, l, 0)?;
        cache.kv = (0..self.text.num_layers())
            .map(|_| KvCache::new(2, cache.capacity.max(l + 1)))
            .collect();
        let ds = deep
            .as_ref()
            .map(|(rows, f)| text::Deepstack { rows, features: f });
        let h = self
            .text
            .forward(embeds, &rope, mask.as_ref(), &mut cache.kv, ds)?;
        cache.len = l;
        Ok(self.text.logits(&h)?)
    }

    /// Feeds one token per row (after [`prefill`](Self::prefill)) and returns the next-token
    /// logits, `[batch, vocab]` f32.
    pub fn step(&self, tokens: &[u32], cache: &mut Cache) -> Result<Tensor, ModelError> {
        let b = cache.batch_size();
        if b == 0 {
            return Err(ModelError::InvalidInput("step before prefill".into()));
        }
        if tokens.len() != b {
            return Err(ModelError::InvalidInput(format!(
                "{} tokens for a batch of {b}",
                tokens.len()
            )));
        }
        if let Some(&t) = tokens
            .iter()
            .find(|&&t| t as usize >= self.config.text.vocab_size)
        {
            return Err(ModelError::InvalidInput(format!(
                "token id {t} is outside the vocabulary ({})",
                self.config.text.vocab_size
            )));
        }
        let ids = Tensor::from_slice(tokens, (b, 1), &self.device)?;
        let embeds = self.text.embed(&ids)?;
        let p: Vec<i64> = cache.next_pos.clone();
        let rope = self.text.rope(&[p.clone(), p.clone(), p], b, 1)?;
        let mask = self.mask(&cache.pad, 1, cache.len)?;
        let h = self
            .text
            .forward(embeds, &rope, mask.as_ref(), &mut cache.kv, None)?;
        for p in cache.next_pos.iter_mut() {
            *p += 1;
        }
        cache.len += 1;
        Ok(self.text.logits(&h)?)
    }

    /// Additive mask `[B, 1, L, past + L]`: causal within the new tokens, padding keys hidden.
    /// `None` when nothing is masked (one unpadded token). Masked scores get f32::MIN rather
    /// than -inf so a padded query row with nothing to attend to stays finite.
    fn mask(&self, pad: &[usize], l: usize, past: usize) -> candle_core::Result<Option<Tensor>> {
        if l == 1 && pad.iter().all(|&p| p == 0) {
            return Ok(None);
        }
        let s = past + l;
        let mut m = Vec::with_capacity(pad.len() * l * s);
        for &p in pad {
            for i in 0..l {
                for j in 0..s {
                    let visible = j <= past + i && j >= p;
                    m.push(if visible { 0.0 } else { f32::MIN });
                }
            }
        }
        Ok(Some(Tensor::from_vec(
            m,
            (pad.len(), 1, l, s),
            &self.device,
        )?))
    }
}

fn visual_tokens(grids: &[[usize; 3]], merge: usize) -> usize {
    grids.iter().map(|g| g[0] * g[1] * g[2]).sum::<usize>() / (merge * merge)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rope_index_follows_the_reference_layout() {
        // text(2) | frame 2x2 merged | text(1) | frame 2x2 merged | text(1); video token 9.
        let v = 9;
        let ids = [1, 2, v, v, v, v, 3, v, v, v, v, 4];
        let (p, next) = rope_index(&ids, v, &[[2, 4, 4]], 2).unwrap();
        assert_eq!(p[0], vec![0, 1, 2, 2, 2, 2, 4, 5, 5, 5, 5, 7]);
        assert_eq!(p[1], vec![0, 1, 2, 2, 3, 3, 4, 5, 5, 6, 6, 7]);
        assert_eq!(p[2], vec![0, 1, 2, 3, 2, 3, 4, 5, 6, 5, 6, 7]);
        assert_eq!(next, 8);
        // A wide frame advances by its longer side.
        let (p, next) = rope_index(&[v, v, v, 1], v, &[[1, 2, 6]], 2).unwrap();
        assert_eq!(p[2], vec![0, 1, 2, 3]);
        assert_eq!(next, 4);
    }

    #[test]
    fn rope_index_rejects_mismatched_placeholders() {
        let v = 9;
        assert!(rope_index(&[v, v, v], v, &[[1, 4, 4]], 2).is_err());
        assert!(rope_index(&[1, v, v, v, v], v, &[[2, 4, 4]], 2).is_err());
        assert!(rope_index(&[1, v], v, &[], 2).is_err());
        let (p, n) = rope_index(&[5, 6, 7], v, &[], 2).unwrap();
        assert_eq!((p[0].clone(), n), (vec![0, 1, 2], 3));
    }
}
