//! The LLaMA language model of VideoLLaVA, fed input embeddings (text + projected frames), with a
//! KV cache that lives outside the model so one loaded model serves every request.
//!
//! Owned rather than taken from candle-transformers' `llama` because that one keeps its cache in
//! a struct tied to one sequence layout, builds its causal mask as `seq × seq` (wrong as soon as
//! a multi-token chunk follows cached tokens), and has no padding mask or per-row positions, so
//! it cannot run a left-padded batch. Here a prompt is prefilled in one causal pass, and a batch
//! of prompts of different lengths runs as one left-padded batch with transformers' semantics
//! (pad keys masked, positions counted over real tokens only).

use candle_core::{DType, Device, Module, Tensor};
use candle_nn::{Embedding, Linear, RmsNorm, VarBuilder};

use super::config::{Act, RopeScaling, TextConfig};

/// Per-request decoding state: keys/values of every layer, which cached positions are real
/// tokens (not left padding) and each row's next position id. Reset between requests; the model
/// itself is never mutated.
pub struct KvCache {
    layers: Vec<candle_nn::kv_cache::KvCache>,
    /// `[batch][position]`: true where the cached token is real.
    valid: Vec<Vec<bool>>,
    /// Next rotary position per row (= number of real tokens so far).
    next_pos: Vec<usize>,
    capacity: usize,
}

impl KvCache {
    /// `capacity` is a hint (prompt + new tokens); the cache grows past it if needed.
    pub fn new(num_layers: usize, capacity: usize) -> Self {
        let capacity = capacity.max(16);
        Self {
            layers: (0..num_layers)
                .map(|_| candle_nn::kv_cache::KvCache::new(2, capacity))
                .collect(),
            valid: Vec::new(),
            next_pos: Vec::new(),
            capacity,
        }
    }

    /// Forgets everything, keeping the layer count and capacity hint.
    pub fn reset(&mut self) {
        let n = self.layers.len();
        *self = Self::new(n, self.capacity);
    }

    /// Tokens cached per row (padding included).
    pub fn len(&self) -> usize {
        self.valid.first().map(|v| v.len()).unwrap_or(0)
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Rows in the batch, once something was fed.
    pub fn batch(&self) -> usize {
        self.valid.len()
    }
}

struct Rotary {
    inv_freq: Vec<f32>,
}

impl Rotary {
    fn new(cfg: &TextConfig) -> Self {
        let d = cfg.head_dim;
        let mut inv: Vec<f32> = (0..d)
            .step_by(2)
            .map(|i| (1.0 / cfg.rope_theta.powf(i as f64 / d as f64)) as f32)
            .collect();
        match &cfg.rope_scaling {
            RopeScaling::None => {}
            RopeScaling::Linear { factor } => {
                inv.iter_mut().for_each(|f| *f /= *factor as f32);
            }
            RopeScaling::Llama3 {
                factor,
                low_freq_factor,
                high_freq_factor,
                original_max_position_embeddings: omax,
            } => {
                let low_wl = omax / low_freq_factor;
                let high_wl = omax / high_freq_factor;
                inv.iter_mut().for_each(|f| {
                    let freq = *f as f64;
                    let wl = 2.0 * std::f64::consts::PI / freq;
                    let out = if wl < high_wl {
                        freq
                    } else if wl > low_wl {
                        freq / factor
                    } else {
                        let s =
                            (omax / wl - low_freq_factor) / (high_freq_factor - low_freq_factor);
                        (1.0 - s) * freq / factor + s * freq
                    };
                    *f = out as f32;
                });
            }
        }
        Self { inv_freq: inv }
    }

    /// cos/sin `[batch, seq, head_dim / 2]` for per-row positions.
    fn tables(
        &self,
        pos: &[Vec<usize>],
        dtype: DType,
        dev: &Device,
    ) -> candle_core::Result<(Tensor, Tensor)> {
        let (b, t, h) = (pos.len(), pos[0].len(), self.inv_freq.len());
        let mut cos = Vec::with_capacity(b * t * h);
        let mut sin = Vec::with_capacity(b * t * h);
        for row in pos {
            for &p in row {
                for &f in &self.inv_freq {
                    // f32 product as transformers computes it, then cos/sin in f32.
                    let a = p as f32 * f;
                    cos.push(a.cos());
                    sin.push(a.sin());
                }
            }
        }
        let c = Tensor::from_vec(cos, (b, t, h), dev)?.to_dtype(dtype)?;
        let s = Tensor::from_vec(sin, (b, t, h), dev)?.to_dtype(dtype)?;
        Ok((c, s))
    }
}

struct Attention {
    q: Linear,
    k: Linear,
    v: Linear,
    o: Linear,
    heads: usize,
    kv_heads: usize,
    head_dim: usize,
}

fn lin(i: usize, o: usize, bias: bool, vb: VarBuilder) -> candle_core::Result<Linear> {
    if bias {
        candle_nn::linear(i, o, vb)
    } else {
        candle_nn::linear_no_bias(i, o, vb)
    }
}

impl Attention {
    fn load(vb: VarBuilder, c: &TextConfig) -> candle_core::Result<Self> {
        let (h, d) = (c.hidden_size, c.head_dim);
        let b = c.attention_bias;
        Ok(Self {
            q: lin(h, c.num_attention_heads * d, b, vb.pp("q_proj"))?,
            k: lin(h, c.num_key_value_heads * d, b, vb.pp("k_proj"))?,
            v: lin(h, c.num_key_value_heads * d, b, vb.pp("v_proj"))?,
            o: lin(c.num_attention_heads * d, h, b, vb.pp("o_proj"))?,
            heads: c.num_attention_heads,
            kv_heads: c.num_key_value_heads,
            head_dim: d,
        })
    }

    fn forward(
        &self,
        x: &Tensor,
        cos: &Tensor,
        sin: &Tensor,
        mask: Option<&Tensor>,
        cache: &mut candle_nn::kv_cache::KvCache,
    ) -> candle_core::Result<Tensor> {
        let (b, t, _) = x.dims3()?;
        let (nh, nkv, d) = (self.heads, self.kv_heads, self.head_dim);
        let q = self
            .q
            .forward(x)?
            .reshape((b, t, nh, d))?
            .transpose(1, 2)?
            .contiguous()?;
        let k = self
            .k
            .forward(x)?
            .reshape((b, t, nkv, d))?
            .transpose(1, 2)?
            .contiguous()?;
        let v = self
            .v
            .forward(x)?
            .reshape((b, t, nkv, d))?
            .transpose(1, 2)?
            .contiguous()?;
        let q = candle_nn::rotary_emb::rope(&q, cos, sin)?;
        let k = candle_nn::rotary_emb::rope(&k, cos, sin)?;
        let (k, v) = cache.append(&k, &v)?;
        let tk = k.dim(2)?;
        let rep = nh / nkv;
        // Grouped-query attention without materialising repeated keys: query head h reads key
        // head h / rep (transformers' `repeat_kv` order), so the `rep` query heads of one group
        // stack into the row axis of one matmul.
        let qg = q.reshape((b, nkv, rep * t, d))?;
        let scale = (d as f64).powf(-0.5);
        let att = (qg.matmul(&k.t()?)? * scale)?.reshape((b, nh, t, tk))?;
        let dt = att.dtype();
        let att = att.to_dtype(DType::F32)?;
        let att = match mask {
            Some(m) => att.broadcast_add(m)?,
            None => att,
        };
        let att = candle_nn::ops::softmax_last_dim(&att)?.to_dtype(dt)?;
        let y = att
            .reshape((b, nkv, rep * t, tk))?
            .matmul(&v)?
            .reshape((b, nh, t, d))?
            .transpose(1, 2)?
            .reshape((b, t, nh * d))?;
        self.o.forward(&y)
    }
}

struct Mlp {
    gate: Linear,
    up: Linear,
    down: Linear,
    act: Act,
}

impl Mlp {
    fn load(vb: VarBuilder, c: &TextConfig) -> candle_core::Result<Self> {
        let (h, i, b) = (c.hidden_size, c.intermediate_size, c.mlp_bias);
        Ok(Self {
            gate: lin(h, i, b, vb.pp("gate_proj"))?,
            up: lin(h, i, b, vb.pp("up_proj"))?,
            down: lin(i, h, b, vb.pp("down_proj"))?,
            act: Act::from_hf(&c.hidden_act).map_err(candle_core::Error::wrap)?,
        })
    }

    fn forward(&self, x: &Tensor) -> candle_core::Result<Tensor> {
        let g = self.act.apply(&self.gate.forward(x)?)?;
        (g * self.up.forward(x)?)?.apply(&self.down)
    }
}

struct Layer {
    ln1: RmsNorm,
    attn: Attention,
    ln2: RmsNorm,
    mlp: Mlp,
}

/// `LlamaForCausalLM` minus the token embedding lookup the caller does (so visual features can
/// replace placeholder rows first).
pub struct LlamaText {
    embed: Embedding,
    layers: Vec<Layer>,
    norm: RmsNorm,
    lm_head: Linear,
    rotary: Rotary,
    cfg: TextConfig,
    dtype: DType,
    device: Device,
}

/// `-inf` rather than a large finite value: `exp` of a finite huge negative takes libm's slow
/// underflow path (≈10% of a CPU prefill), `exp(-inf)` does not. A left-pad query, whose row
/// would be all `-inf` (NaN after softmax), attends to itself instead; its output is never read.
const MASKED: f32 = f32::NEG_INFINITY;

impl LlamaText {
    /// `vb` points at the `LlamaModel` (`language_model.model` in the hub layout), `head` at
    /// `lm_head` (`None` when the embeddings are tied).
    pub fn load(
        vb: VarBuilder,
        head: Option<VarBuilder>,
        cfg: &TextConfig,
    ) -> candle_core::Result<Self> {
        let h = cfg.hidden_size;
        let embed = candle_nn::embedding(cfg.vocab_size, h, vb.pp("embed_tokens"))?;
        let eps = cfg.rms_norm_eps;
        let layers = (0..cfg.num_hidden_layers)
            .map(|l| {
                let lv = vb.pp("layers").pp(l);
                Ok(Layer {
                    ln1: candle_nn::rms_norm(h, eps, lv.pp("input_layernorm"))?,
                    attn: Attention::load(lv.pp("self_attn"), cfg)?,
                    ln2: candle_nn::rms_norm(h, eps, lv.pp("post_attention_layernorm"))?,
                    mlp: Mlp::load(lv.pp("mlp"), cfg)?,
                })
            })
            .collect::<candle_core::Result<_>>()?;
        let norm = candle_nn::rms_norm(h, eps, vb.pp("norm"))?;
        let lm_head = match head {
            Some(hv) => candle_nn::linear_no_bias(h, cfg.vocab_size, hv)?,
            None => Linear::new(embed.embeddings().clone(), None),
        };
        Ok(Self {
            dtype: embed.embeddings().dtype(),
            device: embed.embeddings().device().clone(),
            embed,
            layers,
            norm,
            lm_head,
            rotary: Rotary::new(cfg),
            cfg: cfg.clone(),
        })
    }

    pub fn config(&self) -> &TextConfig {
        &self.cfg
    }

    pub fn dtype(&self) -> DType {
        self.dtype
    }

    pub fn device(&self) -> &Device {
        &self.device
    }

    pub fn new_cache(&self, capacity: usize) -> KvCache {
        KvCache::new(self.cfg.num_hidden_layers, capacity)
    }

    /// Token embeddings `[batch, seq, hidden]`.
    pub fn embed(&self, ids: &Tensor) -> candle_core::Result<Tensor> {
        self.embed.forward(ids)
    }

    /// Runs `embeds` (`[batch, seq, hidden]`) after what `cache` holds, causally, and returns
    /// the logits of each row's last position (`[batch, vocab]`, f32). `valid[b][i]` says
    /// whether input position `i` of row `b` is a real token (false only for left padding).
    pub fn forward(
        &self,
        embeds: &Tensor,
        valid: &[Vec<bool>],
        cache: &mut KvCache,
    ) -> candle_core::Result<Tensor> {
        let (b, t, _) = embeds.dims3()?;
        if valid.len() != b || valid.iter().any(|v| v.len() != t) {
            candle_core::bail!("validity mask does not match the input shape [{b}, {t}]");
        }
        if !cache.is_empty() && cache.batch() != b {
            candle_core::bail!("batch of {b} fed to a cache holding {} rows", cache.batch());
        }
        if cache.is_empty() {
            cache.valid = vec![Vec::new(); b];
            cache.next_pos = vec![0; b];
        }
        let past = cache.len();
        // Positions count real tokens only (transformers: cumsum(mask) - 1, padding at 0).
        let mut pos = vec![vec![0usize; t]; b];
        for (r, row) in valid.iter().enumerate() {
            for (i, &ok) in row.iter().enumerate() {
                if ok {
                    pos[r][i] = cache.next_pos[r];
                    cache.next_pos[r] += 1;
                }
            }
            cache.valid[r].extend_from_slice(row);
        }
        let (cos, sin) = self.rotary.tables(&pos, self.dtype, &self.device)?;
        let tk = past + t;
        // The additive mask is needed for a multi-token chunk (causality) or any padding.
        let any_pad = cache.valid.iter().any(|r| r.iter().any(|&v| !v));
        let mask = if t > 1 || any_pad {
            let mut m = vec![0f32; b * t * tk];
            for r in 0..b {
                for i in 0..t {
                    for j in 0..tk {
                        let own = j == past + i;
                        let pad_query = !cache.valid[r][past + i];
                        let visible = cache.valid[r][j] || (own && pad_query);
                        if j > past + i || !visible {
                            m[(r * t + i) * tk + j] = MASKED;
                        }
                    }
                }
            }
            Some(Tensor::from_vec(m, (b, 1, t, tk), &self.device)?)
        } else {
            None
        };
        let mut x = embeds.to_dtype(self.dtype)?;
        for (layer, kv) in self.layers.iter().zip(cache.layers.iter_mut()) {
            let r = x.clone();
            let h = layer.ln1.forward(&x)?;
            let h = layer.attn.forward(&h, &cos, &sin, mask.as_ref(), kv)?;
            x = (r + h)?;
            let r = x.clone();
            let h = layer.mlp.forward(&layer.ln2.forward(&x)?)?;
            x = (r + h)?;
        }
        let last = x.narrow(1, t - 1, 1)?.squeeze(1)?;
        let last = self.norm.forward(&last)?;
        self.lm_head.forward(&last)?.to_dtype(DType::F32)
    }

    /// Feeds `embeds` one position at a time and returns the logits after each
    /// (`[batch, seq, vocab]`): the slow path a one-pass prefill must agree with.
    pub fn forward_stepwise(
        &self,
        embeds: &Tensor,
        valid: &[Vec<bool>],
        cache: &mut KvCache,
    ) -> candle_core::Result<Tensor> {
        let (b, t, _) = embeds.dims3()?;
        let mut outs = Vec::with_capacity(t);
        for i in 0..t {
            let chunk = embeds.narrow(1, i, 1)?;
            let v: Vec<Vec<bool>> = valid.iter().map(|r| vec![r[i]]).collect();
            outs.push(self.forward(&chunk, &v, cache)?.unsqueeze(1)?);
        }
        let all = Tensor::cat(&outs, 1)?;
        debug_assert_eq!(all.dims3()?.0, b);
        Ok(all)
    }
}
