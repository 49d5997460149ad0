//! The visual side of VLAAD (Video-LLaMA's): EVA ViT-g per frame (the repository's
//! `eva_vit.VisionTransformer`: pre-norm blocks, a bias-free `qkv` with separate `q_bias` and
//! `v_bias`, exact GELU, no final norm), BLIP-2's `ln_vision`, and the BERT Q-Formers run on
//! learned queries only (`Qformer.BertModel` with `query_embeds`: self-attention, cross-attention
//! to the encoder states every `cross_attention_freq` layers, the query feed-forward).

use candle_core::{Module, Tensor};
use candle_nn::{LayerNorm, Linear, VarBuilder};

use super::config::{EvaConfig, QformerConfig};

/// Softmax attention of `q` over `k`/`v`, all `[b, heads, n, d]`, with `q` already scaled.
fn attend(q: &Tensor, k: &Tensor, v: &Tensor) -> candle_core::Result<Tensor> {
    let s = q.contiguous()?.matmul(&k.t()?.contiguous()?)?;
    let p = candle_nn::ops::softmax_last_dim(&s)?;
    p.matmul(&v.contiguous()?)
}

/// `[b, n, heads·d]` → `[b, heads, n, d]`.
fn heads(x: &Tensor, h: usize) -> candle_core::Result<Tensor> {
    let (b, n, c) = x.dims3()?;
    x.reshape((b, n, h, c / h))?.transpose(1, 2)
}

/// `[b, heads, n, d]` → `[b, n, heads·d]`.
fn merge(x: &Tensor) -> candle_core::Result<Tensor> {
    let (b, h, n, d) = x.dims4()?;
    x.transpose(1, 2)?.contiguous()?.reshape((b, n, h * d))
}

struct EvaBlock {
    norm1: LayerNorm,
    qkv_w: Tensor,
    qkv_b: Tensor,
    proj: Linear,
    norm2: LayerNorm,
    fc1: Linear,
    fc2: Linear,
    heads: usize,
    scale: f64,
}

impl EvaBlock {
    fn load(vb: VarBuilder, c: &EvaConfig) -> candle_core::Result<Self> {
        let d = c.embed_dim;
        let a = vb.pp("attn");
        let qkv_w = a.pp("qkv").get((3 * d, d), "weight")?;
        let qb = a.get(d, "q_bias")?;
        let vbias = a.get(d, "v_bias")?;
        // The repository's bias: (q_bias, zeros, v_bias).
        let qkv_b = Tensor::cat(&[&qb, &qb.zeros_like()?, &vbias], 0)?;
        Ok(Self {
            norm1: candle_nn::layer_norm(d, c.layer_norm_eps, vb.pp("norm1"))?,
            qkv_w,
            qkv_b,
            proj: candle_nn::linear(d, d, a.pp("proj"))?,
            norm2: candle_nn::layer_norm(d, c.layer_norm_eps, vb.pp("norm2"))?,
            fc1: candle_nn::linear(d, c.mlp_hidden(), vb.pp("mlp").pp("fc1"))?,
            fc2: candle_nn::linear(c.mlp_hidden(), d, vb.pp("mlp").pp("fc2"))?,
            heads: c.num_heads,
            scale: ((d / c.num_heads) as f64).powf(-0.5),
        })
    }

    fn forward(&self, x: &Tensor) -> candle_core::Result<Tensor> {
        let (b, n, d) = x.dims3()?;
        let h = self.norm1.forward(x)?;
        let qkv = h
            .broadcast_matmul(&self.qkv_w.t()?)?
            .broadcast_add(&self.qkv_b)?
            .reshape((b, n, 3, d))?;
        let q = heads(&qkv.narrow(2, 0, 1)?.squeeze(2)?, self.heads)?;
        let k = heads(&qkv.narrow(2, 1, 1)?.squeeze(2)?, self.heads)?;
        let v = heads(&qkv.narrow(2, 2, 1)?.squeeze(2)?, self.heads)?;
        let o = merge(&attend(&(q * self.scale)?, &k, &v)?)?;
        let x = (x + self.proj.forward(&o)?)?;
        let m = self
            .fc2
            .forward(&self.fc1.forward(&self.norm2.forward(&x)?)?.gelu_erf()?)?;
        x + m
    }
}

/// EVA ViT-g: patch embedding (a stride-`p` convolution, here a matmul over patches), CLS, the
/// absolute positions, the blocks.
pub struct EvaVit {
    patch_w: Tensor,
    patch_b: Tensor,
    cls: Tensor,
    pos: Tensor,
    blocks: Vec<EvaBlock>,
    cfg: EvaConfig,
    img: usize,
}

impl EvaVit {
    /// `vb` at the `VisionTransformer` (`visual_encoder` in the model).
    pub fn load(vb: VarBuilder, c: &EvaConfig, img: usize) -> candle_core::Result<Self> {
        let (d, p) = (c.embed_dim, c.patch_size);
        let g = img / p;
        Ok(Self {
            patch_w: vb
                .pp("patch_embed")
                .pp("proj")
                .get((d, 3, p, p), "weight")?
                .reshape((d, 3 * p * p))?,
            patch_b: vb.pp("patch_embed").pp("proj").get(d, "bias")?,
            cls: vb.get((1, 1, d), "cls_token")?,
            pos: vb.get((1, g * g + 1, d), "pos_embed")?,
            blocks: (0..c.depth)
                .map(|i| EvaBlock::load(vb.pp("blocks").pp(i), c))
                .collect::<candle_core::Result<_>>()?,
            cfg: c.clone(),
            img,
        })
    }

    /// `[n, 3, S, S]` → `[n, 1 + (S/p)², embed_dim]`.
    pub fn forward(&self, px: &Tensor) -> candle_core::Result<Tensor> {
        let (n, c, hh, ww) = px.dims4()?;
        let p = self.cfg.patch_size;
        if c != 3 || hh != self.img || ww != self.img {
            candle_core::bail!(
                "pixel values {:?} do not fit the ViT (3x{1}x{1})",
                px.dims(),
                self.img
            );
        }
        let g = self.img / p;
        let d = self.cfg.embed_dim;
        let patches = px
            .to_dtype(self.patch_w.dtype())?
            .reshape((n, 3, g, p, g, p))?
            .permute((0, 2, 4, 1, 3, 5))?
            .contiguous()?
            .reshape((n * g * g, 3 * p * p))?;
        let x = patches
            .matmul(&self.patch_w.t()?)?
            .broadcast_add(&self.patch_b)?
            .reshape((n, g * g, d))?;
        let cls = self.cls.expand((n, 1, d))?;
        let mut x = Tensor::cat(&[&cls, &x], 1)?.broadcast_add(&self.pos)?;
        for b in &self.blocks {
            x = b.forward(&x)?;
        }
        Ok(x)
    }
}

/// BERT's attention block: `self` (query/key/value) and `output` (dense + residual norm).
struct BertAttention {
    q: Linear,
    k: Linear,
    v: Linear,
    out: Linear,
    norm: LayerNorm,
    heads: usize,
    scale: f64,
}

impl BertAttention {
    fn load(vb: VarBuilder, c: &QformerConfig, kv_width: usize) -> candle_core::Result<Self> {
        let h = c.hidden_size;
        let s = vb.pp("self");
        Ok(Self {
            q: candle_nn::linear(h, h, s.pp("query"))?,
            k: candle_nn::linear(kv_width, h, s.pp("key"))?,
            v: candle_nn::linear(kv_width, h, s.pp("value"))?,
            out: candle_nn::linear(h, h, vb.pp("output").pp("dense"))?,
            norm: candle_nn::layer_norm(h, c.layer_norm_eps, vb.pp("output").pp("LayerNorm"))?,
            heads: c.num_attention_heads,
            scale: 1.0 / ((h / c.num_attention_heads) as f64).sqrt(),
        })
    }

    /// Attention of `x` over `kv` (itself for self-attention), no mask (all positions valid).
    fn forward(&self, x: &Tensor, kv: &Tensor) -> candle_core::Result<Tensor> {
        let q = heads(&self.q.forward(x)?, self.heads)?;
        let k = heads(&self.k.forward(kv)?, self.heads)?;
        let v = heads(&self.v.forward(kv)?, self.heads)?;
        // BERT scales the scores, not the query; the same up to rounding.
        let s = q.contiguous()?.matmul(&k.t()?.contiguous()?)?;
        let p = candle_nn::ops::softmax_last_dim(&(s * self.scale)?)?;
        let o = merge(&p.matmul(&v.contiguous()?)?)?;
        self.norm.forward(&(self.out.forward(&o)? + x)?)
    }
}

struct QformerLayer {
    attn: BertAttention,
    cross: Option<BertAttention>,
    inter: Linear,
    out: Linear,
    norm: LayerNorm,
}

/// A Q-Former on learned queries: `query_embeds` → `LayerNorm` → layers.
pub struct Qformer {
    norm: LayerNorm,
    layers: Vec<QformerLayer>,
}

impl Qformer {
    /// `vb` at `bert`; `encoder_width` is the width of the states the queries read.
    pub fn load(
        vb: VarBuilder,
        c: &QformerConfig,
        layers: usize,
        cross_freq: usize,
        encoder_width: usize,
    ) -> candle_core::Result<Self> {
        let h = c.hidden_size;
        let norm = candle_nn::layer_norm(h, c.layer_norm_eps, vb.pp("embeddings").pp("LayerNorm"))?;
        let layers = (0..layers)
            .map(|i| {
                let l = vb.pp("encoder").pp("layer").pp(i);
                Ok(QformerLayer {
                    attn: BertAttention::load(l.pp("attention"), c, h)?,
                    cross: if i % cross_freq == 0 {
                        Some(BertAttention::load(
                            l.pp("crossattention"),
                            c,
                            encoder_width,
                        )?)
                    } else {
                        None
                    },
                    inter: candle_nn::linear(
                        h,
                        c.intermediate_size,
                        l.pp("intermediate_query").pp("dense"),
                    )?,
                    out: candle_nn::linear(
                        c.intermediate_size,
                        h,
                        l.pp("output_query").pp("dense"),
                    )?,
                    norm: candle_nn::layer_norm(
                        h,
                        c.layer_norm_eps,
                        l.pp("output_query").pp("LayerNorm"),
                    )?,
                })
            })
            .collect::<candle_core::Result<_>>()?;
        Ok(Self { norm, layers })
    }

    /// `queries` `[b, q, h]` reading `states` `[b, n, w]` → `[b, q, h]`.
    pub fn forward(&self, queries: &Tensor, states: &Tensor) -> candle_core::Result<Tensor> {
        let mut x = self.norm.forward(queries)?;
        for l in &self.layers {
            x = l.attn.forward(&x, &x)?;
            if let Some(c) = &l.cross {
                x = c.forward(&x, states)?;
            }
            let f = l.out.forward(&l.inter.forward(&x)?.gelu_erf()?)?;
            x = l.norm.forward(&(f + &x)?)?;
        }
        Ok(x)
    }
}
