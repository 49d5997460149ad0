//! VideoLLaMA2's spatial-temporal convolution connector (`STCConnector` in the repository's
//! `projector.py`): a RegNet stage over each frame's patch grid, a 3-D convolution that halves
//! time, height and width, a second RegNet stage, and a two-layer GELU readout into the LLM.
//!
//! The stages are timm 1.0's `RegStage` as the connector builds it: `Bottleneck` blocks with a
//! bottleneck ratio of 1 and group size 1 (so the 3×3 convolution is depthwise), a
//! squeeze-excitation of `round(in · 0.25)` channels, `LayerNorm2d` + SiLU after each
//! convolution (timm's `LayerNormAct2d`, eps 1e-5) and a 1×1 projection shortcut where the
//! width changes. Everything runs channels-last (`[n, h, w, c]`): the 1×1 convolutions are
//! matmuls, the norm is a plain layer norm over the last axis, and the depthwise 3×3 is nine
//! shifted multiply-adds.

use candle_core::{Module, Tensor};
use candle_nn::{LayerNorm, Linear, VarBuilder};

use super::config::VideoLlama2Config;

/// A 1×1 convolution as a matmul over the channel axis of `[.., c]`.
struct Pointwise {
    w: Tensor,
    b: Option<Tensor>,
}

impl Pointwise {
    fn load(vb: VarBuilder, cin: usize, cout: usize, bias: bool) -> candle_core::Result<Self> {
        let w = vb.get((cout, cin, 1, 1), "weight")?.reshape((cout, cin))?;
        let b = if bias {
            Some(vb.get(cout, "bias")?)
        } else {
            None
        };
        Ok(Self { w: w.t()?, b })
    }

    fn forward(&self, x: &Tensor) -> candle_core::Result<Tensor> {
        let y = x.broadcast_matmul(&self.w)?;
        match &self.b {
            Some(b) => y.broadcast_add(b),
            None => Ok(y),
        }
    }
}

/// timm's `ConvNormAct` with `LayerNormAct2d`: conv (no bias) → layer norm over channels →
/// SiLU unless `act` is off.
struct ConvNormAct {
    conv: Conv,
    norm: LayerNorm,
    act: bool,
}

enum Conv {
    Point(Pointwise),
    /// Depthwise 3×3, stride 1, padding 1: weight `[c, 3, 3]`.
    Depth3(Tensor),
}

impl ConvNormAct {
    fn forward(&self, x: &Tensor) -> candle_core::Result<Tensor> {
        let y = match &self.conv {
            Conv::Point(p) => p.forward(x)?,
            Conv::Depth3(w) => depthwise3(x, w)?,
        };
        let y = self.norm.forward(&y)?;
        if self.act {
            candle_nn::ops::silu(&y)
        } else {
            Ok(y)
        }
    }
}

/// Depthwise 3×3 convolution with zero padding 1 on `[n, h, w, c]`, weight `[c, 3, 3]`.
fn depthwise3(x: &Tensor, w: &Tensor) -> candle_core::Result<Tensor> {
    let (_, h, wd, _) = x.dims4()?;
    let xp = x.pad_with_zeros(1, 1, 1)?.pad_with_zeros(2, 1, 1)?;
    let mut acc: Option<Tensor> = None;
    for dy in 0..3 {
        for dx in 0..3 {
            let tap = w.narrow(1, dy, 1)?.narrow(2, dx, 1)?.flatten_all()?;
            let term = xp
                .narrow(1, dy, h)?
                .narrow(2, dx, wd)?
                .broadcast_mul(&tap)?;
            acc = Some(match acc {
                None => term,
                Some(a) => (a + term)?,
            });
        }
    }
    Ok(acc.expect("nine taps"))
}

fn conv_norm_act(
    vb: VarBuilder,
    cin: usize,
    cout: usize,
    depthwise: bool,
    act: bool,
) -> candle_core::Result<ConvNormAct> {
    let conv = if depthwise {
        Conv::Depth3(
            vb.pp("conv")
                .get((cout, 1, 3, 3), "weight")?
                .reshape((cout, 3, 3))?,
        )
    } else {
        Conv::Point(Pointwise::load(vb.pp("conv"), cin, cout, false)?)
    };
    let norm = candle_nn::layer_norm(cout, 1e-5, vb.pp("bn"))?;
    Ok(ConvNormAct { conv, norm, act })
}

/// timm's RegNet `Bottleneck` (bottle_ratio 1, group_size 1, se_ratio 0.25, SiLU).
struct Bottleneck {
    conv1: ConvNormAct,
    conv2: ConvNormAct,
    se_fc1: Pointwise,
    se_fc2: Pointwise,
    conv3: ConvNormAct,
    shortcut: Option<ConvNormAct>,
}

impl Bottleneck {
    fn load(vb: VarBuilder, cin: usize, cout: usize) -> candle_core::Result<Self> {
        let se = ((cin as f64) * 0.25).round() as usize;
        let shortcut = if cin != cout {
            Some(conv_norm_act(vb.pp("downsample"), cin, cout, false, false)?)
        } else {
            None
        };
        Ok(Self {
            conv1: conv_norm_act(vb.pp("conv1"), cin, cout, false, true)?,
            conv2: conv_norm_act(vb.pp("conv2"), cout, cout, true, true)?,
            se_fc1: Pointwise::load(vb.pp("se").pp("fc1"), cout, se.max(1), true)?,
            se_fc2: Pointwise::load(vb.pp("se").pp("fc2"), se.max(1), cout, true)?,
            conv3: conv_norm_act(vb.pp("conv3"), cout, cout, false, false)?,
            shortcut,
        })
    }

    fn forward(&self, x: &Tensor) -> candle_core::Result<Tensor> {
        let y = self.conv2.forward(&self.conv1.forward(x)?)?;
        // Squeeze-excitation: the mean over the grid gates each channel.
        let s = y.mean_keepdim(1)?.mean_keepdim(2)?;
        let s = candle_nn::ops::silu(&self.se_fc1.forward(&s)?)?;
        let gate = candle_nn::ops::sigmoid(&self.se_fc2.forward(&s)?)?;
        let y = self.conv3.forward(&y.broadcast_mul(&gate)?)?;
        let short = match &self.shortcut {
            Some(s) => s.forward(x)?,
            None => x.clone(),
        };
        candle_nn::ops::silu(&(y + short)?)
    }
}

/// timm's `RegStage`: `depth` bottlenecks, the first changing the width.
struct RegStage(Vec<Bottleneck>);

impl RegStage {
    fn load(vb: VarBuilder, depth: usize, cin: usize, cout: usize) -> candle_core::Result<Self> {
        (0..depth)
            .map(|i| {
                Bottleneck::load(
                    vb.pp(format!("b{}", i + 1)),
                    if i == 0 { cin } else { cout },
                    cout,
                )
            })
            .collect::<candle_core::Result<_>>()
            .map(Self)
    }

    fn forward(&self, x: &Tensor) -> candle_core::Result<Tensor> {
        let mut x = x.clone();
        for b in &self.0 {
            x = b.forward(&x)?;
        }
        Ok(x)
    }
}

/// The connector's depth (RegNet blocks per stage) and downsampling, fixed in the repository.
const DEPTH: usize = 4;
const KT: usize = 2;
const KS: usize = 2;

/// `STCConnector` / `STCConnectorV35`.
pub struct StcConnector {
    s1: RegStage,
    /// Conv3d weight reordered to `[(kt, kh, kw, c_in), c_out]` for channels-last blocks.
    sampler_w: Tensor,
    sampler_b: Tensor,
    s2: RegStage,
    readout1: Linear,
    readout2: Linear,
    padding: usize,
    hidden: usize,
}

impl StcConnector {
    /// `vb` points at `mm_projector`.
    pub fn load(vb: VarBuilder, cfg: &VideoLlama2Config) -> candle_core::Result<Self> {
        let (cin, h) = (cfg.mm_hidden_size, cfg.text.hidden_size);
        let w = vb.pp("sampler").pp("0").get((h, h, KT, KS, KS), "weight")?;
        let sampler_w = w
            .permute((0, 2, 3, 4, 1))?
            .reshape((h, KT * KS * KS * h))?
            .t()?
            .contiguous()?;
        Ok(Self {
            s1: RegStage::load(vb.pp("s1"), DEPTH, cin, h)?,
            sampler_w,
            sampler_b: vb.pp("sampler").pp("0").get(h, "bias")?,
            s2: RegStage::load(vb.pp("s2"), DEPTH, h, h)?,
            readout1: candle_nn::linear(h, h, vb.pp("readout").pp("0"))?,
            readout2: candle_nn::linear(h, h, vb.pp("readout").pp("2"))?,
            padding: cfg.connector.padding(),
            hidden: h,
        })
    }

    /// Frame features `[b, t, h, w, c]` (the tower's patch tokens on their grid) → visual
    /// tokens `[b, t'·h'·w', hidden]` in `(t h w)` order.
    pub fn forward(&self, x: &Tensor) -> candle_core::Result<Tensor> {
        let (b, t, gh, gw, c) = x.dims5()?;
        let hid = self.hidden;
        let y = self.s1.forward(&x.reshape((b * t, gh, gw, c))?)?;
        // Conv3d with kernel = stride: zero-pad, keep whole blocks, and multiply each
        // flattened (kt, kh, kw, c) block by the reordered weight.
        let p = self.padding;
        let y = y
            .reshape((b, t, gh, gw, hid))?
            .pad_with_zeros(1, p, p)?
            .pad_with_zeros(2, p, p)?
            .pad_with_zeros(3, p, p)?;
        let out = |n: usize, k: usize| (n + 2 * p - k) / k + 1;
        let (to, ho, wo) = (out(t, KT), out(gh, KS), out(gw, KS));
        let y = y
            .narrow(1, 0, to * KT)?
            .narrow(2, 0, ho * KS)?
            .narrow(3, 0, wo * KS)?
            .contiguous()?
            .reshape((b * to, KT, ho, KS, wo, KS * hid))?
            .permute((0, 2, 4, 1, 3, 5))?
            .contiguous()?
            .reshape((b * to * ho * wo, KT * KS * KS * hid))?;
        let y = y.matmul(&self.sampler_w)?.broadcast_add(&self.sampler_b)?;
        let y = candle_nn::ops::silu(&y)?.reshape((b * to, ho, wo, hid))?;
        let y = self.s2.forward(&y)?.reshape((b, to * ho * wo, hid))?;
        let y = self.readout1.forward(&y)?.gelu_erf()?;
        self.readout2.forward(&y)
    }
}
