//! A quantized Gemma 3 text decoder, written here because candle 0.11.1's `quantized_gemma3`
//! computes a different model:
//!
//! * its feed-forward uses SiLU where Gemma uses GELU (tanh approximation), so its logits are
//!   not Gemma's (measured on a tiny random file: 0.52 off transformers, at a logit scale of 15;
//!   with GELU this file is within 1e-5);
//! * a multi-token chunk after a cache builds its mask from tensors of two dtypes and fails, so
//!   the system prompt cannot be cached;
//! * single-token decoding ignores the sliding window.
//!
//! Same GGUF tensors and metadata as llama.cpp; the forward pass follows transformers'
//! `Gemma3TextModel` (scaled embeddings, pre- and post-norms around attention and MLP, q/k
//! RMS norms, local layers with their own RoPE base and a sliding window).

use candle_core::quantized::gguf_file::Content;
use candle_core::quantized::QMatMul;
use candle_core::{DType, Device, Module, Result, Tensor};
use candle_nn::Embedding;
use candle_transformers::quantized_nn::RmsNorm;
use std::io::{Read, Seek};

/// Every sixth layer attends globally (Gemma 3's pattern) unless the file says otherwise.
const DEFAULT_SLIDING_PATTERN: usize = 6;
const DEFAULT_LOCAL_ROPE_BASE: f32 = 10_000.0;
const DEFAULT_GLOBAL_ROPE_BASE: f32 = 1_000_000.0;

#[derive(Debug, Clone)]
struct Layer {
    q: QMatMul,
    k: QMatMul,
    v: QMatMul,
    o: QMatMul,
    q_norm: RmsNorm,
    k_norm: RmsNorm,
    attn_norm: RmsNorm,
    post_attn_norm: RmsNorm,
    ffn_norm: RmsNorm,
    post_ffn_norm: RmsNorm,
    gate: QMatMul,
    up: QMatMul,
    down: QMatMul,
    /// `Some(w)`: a query attends to the last `w` positions only.
    window: Option<usize>,
    rope_base: f32,
    cache: Option<(Tensor, Tensor)>,
}

#[derive(Debug, Clone)]
pub struct Gemma3 {
    embed: Embedding,
    embed_scale: f64,
    layers: Vec<Layer>,
    norm: RmsNorm,
    output: QMatMul,
    heads: usize,
    kv_heads: usize,
    head_dim: usize,
    scale: f64,
    device: Device,
}

fn rope_tables(
    base: f32,
    head_dim: usize,
    start: usize,
    len: usize,
    dev: &Device,
) -> Result<(Tensor, Tensor)> {
    let inv: Vec<f32> = (0..head_dim / 2)
        .map(|i| 1.0 / base.powf(2.0 * i as f32 / head_dim as f32))
        .collect();
    let mut angles = Vec::with_capacity(len * inv.len());
    for p in start..start + len {
        angles.extend(inv.iter().map(|f| p as f32 * f));
    }
    let t = Tensor::from_vec(angles, (len, head_dim / 2), dev)?;
    Ok((t.cos()?, t.sin()?))
}

/// Additive mask (len, offset + len): 0 where query `i` (at position offset + i) may see key
/// `j`, minus infinity elsewhere.
fn mask(len: usize, offset: usize, window: Option<usize>, dev: &Device) -> Result<Tensor> {
    let total = offset + len;
    let mut m = vec![0f32; len * total];
    for i in 0..len {
        let qpos = offset + i;
        for j in 0..total {
            let causal = j <= qpos;
            let inside = window.is_none_or(|w| qpos - j.min(qpos) < w);
            if !(causal && inside) {
                m[i * total + j] = f32::NEG_INFINITY;
            }
        }
    }
    Tensor::from_vec(m, (1, 1, len, total), dev)
}

impl Gemma3 {
    pub fn from_gguf<R: Read + Seek>(ct: &Content, r: &mut R, dev: &Device) -> Result<Self> {
        let prefix = ["gemma3", "gemma2", "gemma"]
            .into_iter()
            .find(|p| {
                ct.metadata
                    .contains_key(&format!("{p}.attention.head_count"))
            })
            .unwrap_or("gemma3");
        let md = |k: &str| {
            ct.metadata
                .get(&format!("{prefix}.{k}"))
                .ok_or_else(|| candle_core::Error::Msg(format!("GGUF has no {prefix}.{k}")))
        };
        let heads = md("attention.head_count")?.to_u32()? as usize;
        let kv_heads = md("attention.head_count_kv")?.to_u32()? as usize;
        let layers_n = md("block_count")?.to_u32()? as usize;
        let hidden = md("embedding_length")?.to_u32()? as usize;
        let head_dim = md("attention.key_length")?.to_u32()? as usize;
        let eps = md("attention.layer_norm_rms_epsilon")?.to_f32()? as f64;
        let window = md("attention.sliding_window")?.to_u32()? as usize;
        let pattern = md("attention.sliding_window_type")
            .and_then(|v| v.to_u32())
            .map_or(DEFAULT_SLIDING_PATTERN, |v| v as usize);
        let global_base = md("rope.freq_base")
            .and_then(|v| v.to_f32())
            .unwrap_or(DEFAULT_GLOBAL_ROPE_BASE);
        let local_base = md("rope.local_freq_base")
            .and_then(|v| v.to_f32())
            .unwrap_or(DEFAULT_LOCAL_ROPE_BASE);
        let mut t = |name: &str| ct.tensor(r, name, dev);
        let embed_q = t("token_embd.weight")?;
        let embed = Embedding::new(embed_q.dequantize(dev)?, hidden);
        let norm = RmsNorm::from_qtensor(t("output_norm.weight")?, eps)?;
        let output = match t("output.weight") {
            Ok(w) => QMatMul::from_qtensor(w)?,
            Err(_) => QMatMul::from_qtensor(embed_q)?,
        };
        let mut layers = Vec::with_capacity(layers_n);
        for l in 0..layers_n {
            let mut w = |n: &str| t(&format!("blk.{l}.{n}.weight"));
            let sliding = pattern == 0 || (l + 1) % pattern != 0;
            layers.push(Layer {
                q: QMatMul::from_qtensor(w("attn_q")?)?,
                k: QMatMul::from_qtensor(w("attn_k")?)?,
                v: QMatMul::from_qtensor(w("attn_v")?)?,
                o: QMatMul::from_qtensor(w("attn_output")?)?,
                q_norm: RmsNorm::from_qtensor(w("attn_q_norm")?, eps)?,
                k_norm: RmsNorm::from_qtensor(w("attn_k_norm")?, eps)?,
                attn_norm: RmsNorm::from_qtensor(w("attn_norm")?, eps)?,
                post_attn_norm: RmsNorm::from_qtensor(w("post_attention_norm")?, eps)?,
                ffn_norm: RmsNorm::from_qtensor(w("ffn_norm")?, eps)?,
                post_ffn_norm: RmsNorm::from_qtensor(w("post_ffw_norm")?, eps)?,
                gate: QMatMul::from_qtensor(w("ffn_gate")?)?,
                up: QMatMul::from_qtensor(w("ffn_up")?)?,
                down: QMatMul::from_qtensor(w("ffn_down")?)?,
                window: sliding.then_some(window),
                rope_base: if sliding { local_base } else { global_base },
                cache: None,
            });
        }
        Ok(Self {
            embed,
            embed_scale: (hidden as f64).sqrt(),
            layers,
            norm,
            output,
            heads,
            kv_heads,
            head_dim,
            // llama.cpp and the released configs: query_pre_attn_scalar = head_dim.
            scale: 1.0 / (head_dim as f64).sqrt(),
            device: dev.clone(),
        })
    }

    pub fn clear_kv_cache(&mut self) {
        for l in &mut self.layers {
            l.cache = None;
        }
    }

    /// Logits (b, vocab) for the token after `x` (b, len), which starts at position `offset`.
    pub fn forward(&mut self, x: &Tensor, offset: usize) -> Result<Tensor> {
        let (b, len) = x.dims2()?;
        let mut h = (self.embed.forward(x)? * self.embed_scale)?;
        let (heads, kv_heads, hd) = (self.heads, self.kv_heads, self.head_dim);
        for layer in &mut self.layers {
            let res = h.clone();
            let a = layer.attn_norm.forward(&h)?;
            let q = layer
                .q
                .forward(&a)?
                .reshape((b, len, heads, hd))?
                .transpose(1, 2)?;
            let k = layer
                .k
                .forward(&a)?
                .reshape((b, len, kv_heads, hd))?
                .transpose(1, 2)?;
            let v = layer
                .v
                .forward(&a)?
                .reshape((b, len, kv_heads, hd))?
                .transpose(1, 2)?;
            let q = layer.q_norm.forward(&q.contiguous()?)?;
            let k = layer.k_norm.forward(&k.contiguous()?)?;
            let (cos, sin) = rope_tables(layer.rope_base, hd, offset, len, &self.device)?;
            let q = candle_nn::rotary_emb::rope(&q, &cos, &sin)?;
            let k = candle_nn::rotary_emb::rope(&k, &cos, &sin)?;
            let (k, v) = match &layer.cache {
                Some((kc, vc)) if offset > 0 => (
                    Tensor::cat(&[kc, &k], 2)?,
                    Tensor::cat(&[vc, &v.contiguous()?], 2)?,
                ),
                _ => (k, v.contiguous()?),
            };
            layer.cache = Some((k.clone(), v.clone()));
            let k = candle_transformers::utils::repeat_kv(k, heads / kv_heads)?;
            let v = candle_transformers::utils::repeat_kv(v, heads / kv_heads)?;
            let mut att = (q.matmul(&k.t()?)? * self.scale)?;
            let kv_len = k.dim(2)?;
            let needs_mask = len > 1 || layer.window.is_some_and(|w| kv_len > w);
            if needs_mask {
                att = att.broadcast_add(&mask(len, offset, layer.window, &self.device)?)?;
            }
            let att = candle_nn::ops::softmax_last_dim(&att)?;
            let y = att
                .matmul(&v)?
                .transpose(1, 2)?
                .reshape((b, len, heads * hd))?;
            let y = layer.post_attn_norm.forward(&layer.o.forward(&y)?)?;
            h = (y + res)?;
            let res = h.clone();
            let m = layer.ffn_norm.forward(&h)?;
            let g = layer.gate.forward(&m)?.gelu()?;
            let m = layer.down.forward(&(g * layer.up.forward(&m)?)?)?;
            h = (layer.post_ffn_norm.forward(&m)? + res)?;
        }
        let last = h.narrow(1, len - 1, 1)?.squeeze(1)?;
        let last = self.norm.forward(&last)?;
        self.output.forward(&last)?.to_dtype(DType::F32)
    }
}

#[cfg(test)]
mod tests {
    use super::mask;
    use candle_core::Device;

    #[test]
    fn mask_is_causal_with_offset_and_window() {
        let m = mask(2, 3, Some(3), &Device::Cpu).unwrap();
        let rows: Vec<Vec<f32>> = m.squeeze(0).unwrap().squeeze(0).unwrap().to_vec2().unwrap();
        let seen = |r: &Vec<f32>| r.iter().map(|x| x.is_finite()).collect::<Vec<_>>();
        // Query at position 3 sees 1..=3 (window 3), query at 4 sees 2..=4.
        assert_eq!(seen(&rows[0]), [false, true, true, true, false]);
        assert_eq!(seen(&rows[1]), [false, false, true, true, true]);
        let rows: Vec<Vec<f32>> = mask(2, 1, None, &Device::Cpu)
            .unwrap()
            .squeeze(0)
            .unwrap()
            .squeeze(0)
            .unwrap()
            .to_vec2()
            .unwrap();
        assert_eq!(seen(&rows[0]), [true, true, false]);
        assert_eq!(seen(&rows[1]), [true, true, true]);
    }
}
