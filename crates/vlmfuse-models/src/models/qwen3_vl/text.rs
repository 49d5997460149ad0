//! The Qwen3-VL language model: Qwen3 decoder layers (per-head q/k RMSNorm, GQA, SwiGLU) with
//! interleaved multimodal rotary embeddings, a KV cache, and DeepStack injection of visual
//! features after the first layers.
//!
//! Positions are given by the caller as three rows (temporal, height, width) per token; text
//! tokens carry the same value in all three. Attention is causal over any number of new tokens,
//! so a whole prompt goes through in one call.

use candle_core::{DType, Device, Module, Tensor};
use candle_nn::kv_cache::KvCache;
use candle_nn::{
    embedding, linear_b, rms_norm, Activation, Embedding, Linear, RmsNorm, VarBuilder,
};

use super::config::TextConfig;

struct Attention {
    q_proj: Linear,
    k_proj: Linear,
    v_proj: Linear,
    o_proj: Linear,
    q_norm: RmsNorm,
    k_norm: RmsNorm,
    heads: usize,
    kv_heads: usize,
    head_dim: usize,
}

impl Attention {
    fn new(cfg: &TextConfig, vb: VarBuilder) -> candle_core::Result<Self> {
        let (h, hd) = (cfg.hidden_size, cfg.head_dim);
        let (nh, nkv, bias) = (
            cfg.num_attention_heads,
            cfg.num_key_value_heads,
            cfg.attention_bias,
        );
        Ok(Self {
            q_proj: linear_b(h, nh * hd, bias, vb.pp("q_proj"))?,
            k_proj: linear_b(h, nkv * hd, bias, vb.pp("k_proj"))?,
            v_proj: linear_b(h, nkv * hd, bias, vb.pp("v_proj"))?,
            o_proj: linear_b(nh * hd, h, bias, vb.pp("o_proj"))?,
            q_norm: rms_norm(hd, cfg.rms_norm_eps, vb.pp("q_norm"))?,
            k_norm: rms_norm(hd, cfg.rms_norm_eps, vb.pp("k_norm"))?,
            heads: nh,
            kv_heads: nkv,
            head_dim: hd,
        })
    }

    fn forward(
        &self,
        xs: &Tensor,
        rope: &(Tensor, Tensor),
        mask: Option<&Tensor>,
        cache: &mut KvCache,
    ) -> candle_core::Result<Tensor> {
        let (b, l, _) = xs.dims3()?;
        let (nh, nkv, hd) = (self.heads, self.kv_heads, self.head_dim);
        let heads =
            |proj: &Linear, n: usize, norm: Option<&RmsNorm>| -> candle_core::Result<Tensor> {
                let t = proj.forward(xs)?.reshape((b, l, n, hd))?;
                let t = match norm {
                    Some(norm) => norm.forward(&t)?,
                    None => t,
                };
                t.transpose(1, 2)?.contiguous()
            };
        let q = heads(&self.q_proj, nh, Some(&self.q_norm))?;
        let k = heads(&self.k_proj, nkv, Some(&self.k_norm))?;
        let v = heads(&self.v_proj, nkv, None)?;
        let (cos, sin) = rope;
        let q = candle_nn::rotary_emb::rope(&q, cos, sin)?;
        let k = candle_nn::rotary_emb::rope(&k, cos, sin)?;
        let (k, v) = cache.append(&k, &v)?;
        // GQA without copying the cache: the n_rep query heads that share a key/value head are
        // stacked as extra query rows of that head.
        let rep = nh / nkv;
        let q = q.reshape((b, nkv, rep * l, hd))?;
        let scale = 1.0 / (hd as f64).sqrt();
        let o = super::attention_grouped(&q, &k, &v, scale, mask, rep)?;
        let o = o
            .reshape((b, nh, l, hd))?
            .transpose(1, 2)?
            .reshape((b, l, nh * hd))?;
        self.o_proj.forward(&o)
    }
}

struct Layer {
    input_layernorm: RmsNorm,
    post_attention_layernorm: RmsNorm,
    attn: Attention,
    gate_proj: Linear,
    up_proj: Linear,
    down_proj: Linear,
    act: Activation,
}

impl Layer {
    fn new(cfg: &TextConfig, vb: VarBuilder) -> candle_core::Result<Self> {
        let (h, i) = (cfg.hidden_size, cfg.intermediate_size);
        Ok(Self {
            input_layernorm: rms_norm(h, cfg.rms_norm_eps, vb.pp("input_layernorm"))?,
            post_attention_layernorm: rms_norm(
                h,
                cfg.rms_norm_eps,
                vb.pp("post_attention_layernorm"),
            )?,
            attn: Attention::new(cfg, vb.pp("self_attn"))?,
            gate_proj: linear_b(h, i, false, vb.pp("mlp.gate_proj"))?,
            up_proj: linear_b(h, i, false, vb.pp("mlp.up_proj"))?,
            down_proj: linear_b(i, h, false, vb.pp("mlp.down_proj"))?,
            act: cfg.hidden_act,
        })
    }

    fn forward(
        &self,
        xs: &Tensor,
        rope: &(Tensor, Tensor),
        mask: Option<&Tensor>,
        cache: &mut KvCache,
    ) -> candle_core::Result<Tensor> {
        let a = self
            .attn
            .forward(&self.input_layernorm.forward(xs)?, rope, mask, cache)?;
        let xs = (xs + a)?;
        let h = self.post_attention_layernorm.forward(&xs)?;
        let m = (crate::ops::activation(self.act, &self.gate_proj.forward(&h)?)?
            * self.up_proj.forward(&h)?)?;
        xs + self.down_proj.forward(&m)?
    }
}

/// Which position row (0 = temporal, 1 = height, 2 = width) drives each of the `half`
/// rotary frequencies: interleaved T H W T H W ..., height and width only up to 3 x their
/// section, every other frequency temporal (`Qwen3VLTextRotaryEmbedding.recomposition_frequencies`).
pub fn frequency_axes(section: [usize; 3], half: usize) -> Vec<usize> {
    let [_, sh, sw] = section;
    (0..half)
        .map(|j| {
            if j % 3 == 1 && j < 3 * sh {
                1
            } else if j % 3 == 2 && j < 3 * sw {
                2
            } else {
                0
            }
        })
        .collect()
}

/// DeepStack features for one forward call: flat row indices (`batch * seq + pos`) of the
/// visual placeholders and, per leading layer, the rows to add there.
pub struct Deepstack<'a> {
    pub rows: &'a Tensor,
    pub features: &'a [Tensor],
}

pub struct TextModel {
    embed_tokens: Embedding,
    layers: Vec<Layer>,
    norm: RmsNorm,
    lm_head: Linear,
    inv_freq: Vec<f32>,
    mrope_section: [usize; 3],
    device: Device,
    dtype: DType,
}

impl TextModel {
    /// `vb` at the checkpoint root (`model.language_model.*`, `lm_head.*`).
    pub fn new(
        cfg: &TextConfig,
        tie_word_embeddings: bool,
        vb: VarBuilder,
    ) -> candle_core::Result<Self> {
        let m = vb.pp("model.language_model");
        let embed_tokens = embedding(cfg.vocab_size, cfg.hidden_size, m.pp("embed_tokens"))?;
        let layers = (0..cfg.num_hidden_layers)
            .map(|i| Layer::new(cfg, m.pp(format!("layers.{i}"))))
            .collect::<candle_core::Result<Vec<_>>>()?;
        let norm = rms_norm(cfg.hidden_size, cfg.rms_norm_eps, m.pp("norm"))?;
        let lm_head = if tie_word_embeddings {
            Linear::new(embed_tokens.embeddings().clone(), None)
        } else {
            linear_b(cfg.hidden_size, cfg.vocab_size, false, vb.pp("lm_head"))?
        };
        // As the reference computes it: f32 `base ** (arange(0, d, 2) / d)`.
        let d = cfg.head_dim;
        let inv_freq = (0..d)
            .step_by(2)
            .map(|i| 1.0 / (cfg.rope_theta as f32).powf(i as f32 / d as f32))
            .collect();
        Ok(Self {
            embed_tokens,
            layers,
            norm,
            lm_head,
            inv_freq,
            mrope_section: cfg.mrope_section,
            device: vb.device().clone(),
            dtype: vb.dtype(),
        })
    }

    pub fn num_layers(&self) -> usize {
        self.layers.len()
    }

    pub fn dtype(&self) -> DType {
        self.dtype
    }

    pub fn embed(&self, ids: &Tensor) -> candle_core::Result<Tensor> {
        self.embed_tokens.forward(ids)
    }

    /// See [`frequency_axes`].
    pub fn frequency_axes(&self) -> Vec<usize> {
        frequency_axes(self.mrope_section, self.inv_freq.len())
    }

    /// cos/sin `[batch, seq, head_dim / 2]` for positions `pos[axis][b * seq + i]`.
    pub fn rope(
        &self,
        pos: &[Vec<i64>; 3],
        batch: usize,
        seq: usize,
    ) -> candle_core::Result<(Tensor, Tensor)> {
        let axes = self.frequency_axes();
        let half = self.inv_freq.len();
        let n = batch * seq;
        let mut cos = Vec::with_capacity(n * half);
        let mut sin = Vec::with_capacity(n * half);
        if pos.iter().any(|p| p.len() != n) {
            candle_core::bail!("position rows must hold {n} entries");
        }
        for ((&t, &h), &w) in pos[0].iter().zip(&pos[1]).zip(&pos[2]) {
            let p = [t, h, w];
            for (&axis, &f) in axes.iter().zip(&self.inv_freq) {
                let angle = p[axis] as f32 * f;
                cos.push(angle.cos());
                sin.push(angle.sin());
            }
        }
        let cos = Tensor::from_vec(cos, (batch, seq, half), &self.device)?.to_dtype(self.dtype)?;
        let sin = Tensor::from_vec(sin, (batch, seq, half), &self.device)?.to_dtype(self.dtype)?;
        Ok((cos, sin))
    }

    /// Runs the decoder over `embeds` (`[batch, seq, hidden]`) and returns the final-norm hidden
    /// state of the last position of every row (`[batch, hidden]`).
    pub fn forward(
        &self,
        embeds: Tensor,
        rope: &(Tensor, Tensor),
        mask: Option<&Tensor>,
        caches: &mut [KvCache],
        deepstack: Option<Deepstack<'_>>,
    ) -> candle_core::Result<Tensor> {
        let (b, l, h) = embeds.dims3()?;
        let mut xs = embeds;
        for (i, (layer, cache)) in self.layers.iter().zip(caches.iter_mut()).enumerate() {
            xs = layer.forward(&xs, rope, mask, cache)?;
            if let Some(ds) = &deepstack {
                if let Some(f) = ds.features.get(i) {
                    xs = xs
                        .reshape((b * l, h))?
                        .index_add(ds.rows, &f.to_dtype(xs.dtype())?, 0)?
                        .reshape((b, l, h))?;
                }
            }
        }
        let last = xs.narrow(1, l - 1, 1)?.squeeze(1)?;
        self.norm.forward(&last)
    }

    /// Next-token logits (`[batch, vocab]`, f32) from [`forward`](Self::forward)'s output.
    pub fn logits(&self, hidden: &Tensor) -> candle_core::Result<Tensor> {
        self.lm_head.forward(hidden)?.to_dtype(DType::F32)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn released_checkpoints_interleave_t_h_w_and_end_temporal() {
        // [24, 20, 20] over 64 frequencies: T H W repeated 20 times, then the last four T.
        let a = frequency_axes([24, 20, 20], 64);
        for (j, &x) in a.iter().enumerate().take(60) {
            assert_eq!(x, j % 3, "frequency {j}");
        }
        assert_eq!(&a[60..], &[0, 0, 0, 0]);
        assert_eq!(frequency_axes([2, 1, 1], 4), vec![0, 1, 2, 0]);
    }
}
