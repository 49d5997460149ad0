//! The CLIP vision tower of VideoLLaVA (one per modality: `video_tower`, `image_tower`), and
//! the two-layer projector into the language model's embedding space.
//!
//! Owned rather than taken from candle-transformers' `clip::vision_model` because that one
//! returns hidden states without the embedding output, so its index `-2` is the *last* layer
//! (transformers' `hidden_states[-2]` is the second to last: `hidden_states[0]` is the input of
//! layer 1); it also hard-codes `layer_norm_eps` and QuickGELU, and always runs every layer. This
//! tower loads and runs only the layers up to the deepest one the projector reads, so the last
//! layer and `post_layernorm` of a `-2` checkpoint are never touched.

use candle_core::{DType, Module, Tensor, D};
use candle_nn::{LayerNorm, Linear, VarBuilder};

use super::config::{Act, VideoLlavaConfig, VisionConfig};

struct EncoderLayer {
    ln1: LayerNorm,
    q: Linear,
    k: Linear,
    v: Linear,
    out: Linear,
    ln2: LayerNorm,
    fc1: Linear,
    fc2: Linear,
    heads: usize,
    head_dim: usize,
    act: Act,
}

impl EncoderLayer {
    fn load(vb: VarBuilder, c: &VisionConfig) -> candle_core::Result<Self> {
        let h = c.hidden_size;
        let eps = c.layer_norm_eps;
        let a = vb.pp("self_attn");
        Ok(Self {
            ln1: candle_nn::layer_norm(h, eps, vb.pp("layer_norm1"))?,
            q: candle_nn::linear(h, h, a.pp("q_proj"))?,
            k: candle_nn::linear(h, h, a.pp("k_proj"))?,
            v: candle_nn::linear(h, h, a.pp("v_proj"))?,
            out: candle_nn::linear(h, h, a.pp("out_proj"))?,
            ln2: candle_nn::layer_norm(h, eps, vb.pp("layer_norm2"))?,
            fc1: candle_nn::linear(h, c.intermediate_size, vb.pp("mlp").pp("fc1"))?,
            fc2: candle_nn::linear(c.intermediate_size, h, vb.pp("mlp").pp("fc2"))?,
            heads: c.num_attention_heads,
            head_dim: c.head_dim(),
            act: Act::from_hf(&c.hidden_act).map_err(candle_core::Error::wrap)?,
        })
    }

    fn forward(&self, xs: &Tensor) -> candle_core::Result<Tensor> {
        let (n, t, h) = xs.dims3()?;
        let r = xs;
        let x = self.ln1.forward(xs)?;
        let split = |y: Tensor| -> candle_core::Result<Tensor> {
            y.reshape((n, t, self.heads, self.head_dim))?
                .transpose(1, 2)?
                .contiguous()
        };
        let q = split(self.q.forward(&x)?)?;
        let k = split(self.k.forward(&x)?)?;
        let v = split(self.v.forward(&x)?)?;
        let scale = (self.head_dim as f64).powf(-0.5);
        let dt = q.dtype();
        // Scores and softmax in f32, as transformers' eager path does for half precision.
        let att = (q.matmul(&k.t()?)? * scale)?.to_dtype(DType::F32)?;
        let att = candle_nn::ops::softmax_last_dim(&att)?.to_dtype(dt)?;
        let y = att
            .matmul(&v)?
            .transpose(1, 2)?
            .reshape((n, t, h))?
            .apply(&self.out)?;
        let x = (r + y)?;
        let m = self.ln2.forward(&x)?.apply(&self.fc1)?;
        let m = self.act.apply(&m)?.apply(&self.fc2)?;
        x + m
    }
}

/// `CLIPVisionModel` up to a given depth.
pub struct ClipTower {
    patch_w: Tensor,
    class_embedding: Tensor,
    position_embedding: Tensor,
    pre_ln: LayerNorm,
    layers: Vec<EncoderLayer>,
    cfg: VisionConfig,
}

impl ClipTower {
    /// `vb` points at the tower's `vision_model` (the legacy hub layout); `depth` layers are
    /// loaded (the deepest hidden state any caller asks for).
    pub fn load(vb: VarBuilder, cfg: &VisionConfig, depth: usize) -> candle_core::Result<Self> {
        let h = cfg.hidden_size;
        let p = cfg.patch_size;
        let e = vb.pp("embeddings");
        let patch_w = e
            .pp("patch_embedding")
            .get((h, cfg.num_channels, p, p), "weight")?
            .reshape((h, cfg.num_channels * p * p))?;
        let class_embedding = e.get(h, "class_embedding")?;
        let position_embedding = e
            .pp("position_embedding")
            .get((cfg.tokens_per_frame(), h), "weight")?;
        let pre_ln = candle_nn::layer_norm(h, cfg.layer_norm_eps, vb.pp("pre_layrnorm"))?;
        let layers = (0..depth.min(cfg.num_hidden_layers))
            .map(|l| EncoderLayer::load(vb.pp("encoder").pp("layers").pp(l), cfg))
            .collect::<candle_core::Result<_>>()?;
        Ok(Self {
            patch_w,
            class_embedding,
            position_embedding,
            pre_ln,
            layers,
            cfg: cfg.clone(),
        })
    }

    /// Embeddings after `pre_layrnorm`: `hidden_states[0]`. The stride-`p` convolution is a
    /// matmul over non-overlapping patches (exact, and far faster than a general conv on CPU).
    fn embed(&self, pixels: &Tensor) -> candle_core::Result<Tensor> {
        let (n, c, hh, ww) = pixels.dims4()?;
        let p = self.cfg.patch_size;
        let s = self.cfg.image_size;
        if hh != s || ww != s || c != self.cfg.num_channels {
            candle_core::bail!(
                "pixel values {:?} do not fit the tower ({}x{s}x{s})",
                pixels.dims(),
                self.cfg.num_channels
            );
        }
        let g = s / p;
        let h = self.cfg.hidden_size;
        let patches = pixels
            .to_dtype(self.patch_w.dtype())?
            .reshape((n, c, g, p, g, p))?
            .permute((0, 2, 4, 1, 3, 5))?
            .contiguous()?
            .reshape((n * g * g, c * p * p))?;
        let pe = patches.matmul(&self.patch_w.t()?)?.reshape((n, g * g, h))?;
        let cls = self.class_embedding.reshape((1, 1, h))?.expand((n, 1, h))?;
        let x = Tensor::cat(&[&cls, &pe], 1)?;
        let x = x.broadcast_add(&self.position_embedding.unsqueeze(0)?)?;
        self.pre_ln.forward(&x)
    }

    /// `hidden_states[i]` for each requested `i` (`0` = embeddings, `L` = last layer), for
    /// frames `[n, 3, S, S]`; runs only as deep as the largest index.
    pub fn hidden_states(
        &self,
        pixels: &Tensor,
        indices: &[usize],
    ) -> candle_core::Result<Vec<Tensor>> {
        let deepest = indices.iter().copied().max().unwrap_or(0);
        if deepest > self.layers.len() {
            candle_core::bail!(
                "hidden state {deepest} asked of a tower loaded to depth {}",
                self.layers.len()
            );
        }
        let mut x = self.embed(pixels)?;
        let mut out: Vec<Option<Tensor>> = vec![None; indices.len()];
        for (depth, layer) in std::iter::once(None)
            .chain(self.layers.iter().map(Some))
            .enumerate()
            .take(deepest + 1)
        {
            if let Some(layer) = layer {
                x = layer.forward(&x)?;
            }
            for (slot, &i) in out.iter_mut().zip(indices) {
                if i == depth {
                    *slot = Some(x.clone());
                }
            }
        }
        Ok(out.into_iter().map(|t| t.expect("filled")).collect())
    }
}

/// `VideoLlavaMultiModalProjector`: linear → activation → linear.
pub struct Projector {
    l1: Linear,
    l2: Linear,
    act: Act,
}

impl Projector {
    pub fn load(vb: VarBuilder, cfg: &VideoLlavaConfig) -> candle_core::Result<Self> {
        let th = cfg.text.hidden_size;
        let lin = |i, o, vb| {
            if cfg.projector_bias {
                candle_nn::linear(i, o, vb)
            } else {
                candle_nn::linear_no_bias(i, o, vb)
            }
        };
        Ok(Self {
            l1: lin(cfg.projector_in(), th, vb.pp("linear_1"))?,
            l2: lin(th, th, vb.pp("linear_2"))?,
            act: cfg.projector_act,
        })
    }

    pub fn forward(&self, xs: &Tensor) -> candle_core::Result<Tensor> {
        let x = self.l1.forward(xs)?;
        self.act.apply(&x)?.apply(&self.l2)
    }
}

/// Concatenates the selected hidden states along the feature axis, as transformers does for a
/// list-valued `vision_feature_layer`.
pub fn concat_features(hs: &[Tensor]) -> candle_core::Result<Tensor> {
    if hs.len() == 1 {
        Ok(hs[0].clone())
    } else {
        Tensor::cat(hs, D::Minus1)
    }
}
