//! The Qwen3-VL vision tower: patch embedding, learned positions resampled to each grid, 2-D
//! rotary attention within each frame, a 2x2 patch merger into the text width, and the DeepStack
//! side outputs of selected blocks.
//!
//! Patches arrive in the processor's order: per temporal group, 2x2 merge blocks in raster order,
//! the four patches of a block consecutive. Positions, rotary angles and the merger all assume it.

use candle_core::{DType, Device, Module, Tensor};
use candle_nn::{layer_norm, linear, Activation, LayerNorm, LayerNormConfig, Linear, VarBuilder};

use super::config::VisionConfig;

/// What the tower hands to the text model for a batch of videos.
#[derive(Debug, Clone)]
pub struct VisionOutput {
    /// `[merged tokens, out_hidden_size]`: one row per `<|video_pad|>` placeholder, videos in
    /// input order.
    pub embeds: Tensor,
    /// One `[merged tokens, out_hidden_size]` tensor per DeepStack layer, added to the hidden
    /// states of text layer `i` at the placeholders.
    pub deepstack: Vec<Tensor>,
}

fn ln(size: usize, vb: VarBuilder) -> candle_core::Result<LayerNorm> {
    layer_norm(
        size,
        LayerNormConfig {
            eps: 1e-6,
            ..Default::default()
        },
        vb,
    )
}

struct Block {
    norm1: LayerNorm,
    norm2: LayerNorm,
    qkv: Linear,
    proj: Linear,
    fc1: Linear,
    fc2: Linear,
    act: Activation,
    heads: usize,
    head_dim: usize,
}

impl Block {
    fn new(cfg: &VisionConfig, vb: VarBuilder) -> candle_core::Result<Self> {
        let h = cfg.hidden_size;
        Ok(Self {
            norm1: ln(h, vb.pp("norm1"))?,
            norm2: ln(h, vb.pp("norm2"))?,
            qkv: linear(h, 3 * h, vb.pp("attn.qkv"))?,
            proj: linear(h, h, vb.pp("attn.proj"))?,
            fc1: linear(h, cfg.intermediate_size, vb.pp("mlp.linear_fc1"))?,
            fc2: linear(cfg.intermediate_size, h, vb.pp("mlp.linear_fc2"))?,
            act: cfg.hidden_act,
            heads: cfg.num_heads,
            head_dim: cfg.head_dim(),
        })
    }

    /// `segments`: per video, (rows, frames); attention never crosses a frame.
    fn forward(
        &self,
        xs: &Tensor,
        segments: &[(usize, usize)],
        cos: &Tensor,
        sin: &Tensor,
    ) -> candle_core::Result<Tensor> {
        let n = xs.dim(0)?;
        let (nh, hd) = (self.heads, self.head_dim);
        let qkv = self
            .qkv
            .forward(&self.norm1.forward(xs)?)?
            .reshape((n, 3, nh, hd))?;
        // The reference rotates in f32 whatever the model dtype.
        let rot = |i: usize| -> candle_core::Result<Tensor> {
            let t = qkv.narrow(1, i, 1)?.squeeze(1)?;
            let dt = t.dtype();
            let t = t.to_dtype(DType::F32)?.unsqueeze(0)?.contiguous()?;
            candle_nn::rotary_emb::rope_thd(&t, cos, sin)?
                .squeeze(0)?
                .to_dtype(dt)
        };
        let q = rot(0)?;
        let k = rot(1)?;
        let v = qkv.narrow(1, 2, 1)?.squeeze(1)?;
        let scale = 1.0 / (hd as f64).sqrt();
        let mut outs = Vec::with_capacity(segments.len());
        let mut start = 0;
        for &(rows, frames) in segments {
            let per = rows / frames;
            // [frames, heads, per, hd]: each frame is one attention batch entry.
            let view = |t: &Tensor| {
                t.narrow(0, start, rows)?
                    .reshape((frames, per, nh, hd))?
                    .transpose(1, 2)?
                    .contiguous()
            };
            let o = super::attention(&view(&q)?, &view(&k)?, &view(&v)?, scale, None)?;
            outs.push(o.transpose(1, 2)?.reshape((rows, nh * hd))?);
            start += rows;
        }
        let attn = Tensor::cat(&outs, 0)?;
        let xs = (xs + self.proj.forward(&attn)?)?;
        let mlp = self.fc2.forward(&crate::ops::activation(
            self.act,
            &self.fc1.forward(&self.norm2.forward(&xs)?)?,
        )?)?;
        xs + mlp
    }
}

/// `Qwen3VLVisionPatchMerger`: LayerNorm (before the 2x2 shuffle for the main merger, after it
/// for the DeepStack ones), then Linear-GELU-Linear into the text width. The GELU is the exact
/// erf form (`nn.GELU()`), not the tanh one of the blocks.
struct Merger {
    norm: LayerNorm,
    postshuffle: bool,
    merged: usize,
    fc1: Linear,
    fc2: Linear,
}

impl Merger {
    fn new(cfg: &VisionConfig, postshuffle: bool, vb: VarBuilder) -> candle_core::Result<Self> {
        let merged = cfg.hidden_size * cfg.spatial_merge_size.pow(2);
        Ok(Self {
            norm: ln(
                if postshuffle { merged } else { cfg.hidden_size },
                vb.pp("norm"),
            )?,
            postshuffle,
            merged,
            fc1: linear(merged, merged, vb.pp("linear_fc1"))?,
            fc2: linear(merged, cfg.out_hidden_size, vb.pp("linear_fc2"))?,
        })
    }

    fn forward(&self, xs: &Tensor) -> candle_core::Result<Tensor> {
        let groups = xs.dim(0)? * xs.dim(1)? / self.merged;
        let xs = if self.postshuffle {
            self.norm.forward(&xs.reshape((groups, self.merged))?)?
        } else {
            self.norm.forward(xs)?.reshape((groups, self.merged))?
        };
        self.fc2.forward(&self.fc1.forward(&xs)?.gelu_erf()?)
    }
}

/// The whole tower.
pub struct VisionModel {
    patch_embed: Linear,
    pos_embed: Tensor,
    blocks: Vec<Block>,
    merger: Merger,
    deepstack: Vec<Merger>,
    deepstack_at: Vec<Option<usize>>,
    inv_freq: Vec<f32>,
    cfg: VisionConfig,
    side: usize,
    device: Device,
}

/// Per-axis taps and weights of `F.interpolate(mode="bilinear", align_corners=True)` from a
/// `side`-long table to `size` samples, computed in f32 like the reference.
fn bilinear_taps(size: usize, side: usize) -> Vec<([usize; 2], [f32; 2])> {
    (0..size)
        .map(|i| {
            // `clamp(size - 1, min=1)` as in the reference: one sample sits on entry 0.
            let src = i as f32 * (side - 1) as f32 / (size.max(2) - 1) as f32;
            let f = src.floor();
            let taps = [(f as usize).min(side - 1), (f as usize + 1).min(side - 1)];
            let w = [
                (1.0 - (src - f)).max(0.0),
                (1.0 - (src - f - 1.0).abs()).max(0.0),
            ];
            (taps, w)
        })
        .collect()
}

impl VisionModel {
    pub fn new(cfg: &VisionConfig, vb: VarBuilder) -> candle_core::Result<Self> {
        let h = cfg.hidden_size;
        // A Conv3d whose kernel equals its stride over exactly one patch is a matmul over the
        // flattened (C, T, P, P) patch row: one GEMM instead of T strided 2-D convolutions.
        let w = vb.get(
            (
                h,
                cfg.in_channels,
                cfg.temporal_patch_size,
                cfg.patch_size,
                cfg.patch_size,
            ),
            "patch_embed.proj.weight",
        )?;
        let b = vb.get(h, "patch_embed.proj.bias")?;
        let patch_embed = Linear::new(w.reshape((h, cfg.patch_dim()))?, Some(b));
        let pos_embed = vb.get((cfg.num_position_embeddings, h), "pos_embed.weight")?;
        let blocks = (0..cfg.depth)
            .map(|i| Block::new(cfg, vb.pp(format!("blocks.{i}"))))
            .collect::<candle_core::Result<Vec<_>>>()?;
        let merger = Merger::new(cfg, false, vb.pp("merger"))?;
        let deepstack = (0..cfg.deepstack_visual_indexes.len())
            .map(|i| Merger::new(cfg, true, vb.pp(format!("deepstack_merger_list.{i}"))))
            .collect::<candle_core::Result<Vec<_>>>()?;
        let mut deepstack_at = vec![None; cfg.depth];
        for (j, &layer) in cfg.deepstack_visual_indexes.iter().enumerate() {
            deepstack_at[layer] = Some(j);
        }
        // Axial rope: a quarter of the head dim per axis, cos/sin laid out [h freqs, w freqs].
        let spatial = cfg.head_dim() / 2;
        let inv_freq = (0..spatial)
            .step_by(2)
            .map(|i| 1.0 / (cfg.rope_theta as f32).powf(i as f32 / spatial as f32))
            .collect();
        let side = (cfg.num_position_embeddings as f64).sqrt().round() as usize;
        Ok(Self {
            patch_embed,
            pos_embed,
            blocks,
            merger,
            deepstack,
            deepstack_at,
            inv_freq,
            cfg: cfg.clone(),
            side,
            device: vb.device().clone(),
        })
    }

    /// (row, col) of every patch of one frame, in merge-block order.
    fn block_order(&self, h: usize, w: usize) -> Vec<(usize, usize)> {
        let m = self.cfg.spatial_merge_size;
        let mut out = Vec::with_capacity(h * w);
        for br in 0..h / m {
            for bc in 0..w / m {
                for ir in 0..m {
                    for ic in 0..m {
                        out.push((br * m + ir, bc * m + ic));
                    }
                }
            }
        }
        out
    }

    /// Learned positions of one frame's patches, bilinearly resampled from the square table.
    fn frame_positions(&self, h: usize, w: usize) -> candle_core::Result<Tensor> {
        let (ty, tx) = (bilinear_taps(h, self.side), bilinear_taps(w, self.side));
        let order = self.block_order(h, w);
        let mut idx: [Vec<u32>; 4] = Default::default();
        let mut wts: [Vec<f32>; 4] = Default::default();
        for &(r, c) in &order {
            let ((ry, wy), (rx, wx)) = (ty[r], tx[c]);
            for a in 0..2 {
                for b in 0..2 {
                    idx[a * 2 + b].push((ry[a] * self.side + rx[b]) as u32);
                    wts[a * 2 + b].push(wy[a] * wx[b]);
                }
            }
        }
        let n = order.len();
        let dtype = self.pos_embed.dtype();
        let mut acc: Option<Tensor> = None;
        for k in 0..4 {
            let i = Tensor::from_slice(&idx[k], n, &self.device)?;
            let wk = Tensor::from_slice(&wts[k], (n, 1), &self.device)?.to_dtype(dtype)?;
            let term = self.pos_embed.index_select(&i, 0)?.broadcast_mul(&wk)?;
            acc = Some(match acc {
                None => term,
                Some(a) => (a + term)?,
            });
        }
        Ok(acc.expect("four taps"))
    }

    /// Runs the tower on the concatenated patch rows of several videos (`grids[i]` = `[t, h, w]`
    /// in patches). Rows must number `sum(t * h * w)`.
    pub fn forward(
        &self,
        pixels: &Tensor,
        grids: &[[usize; 3]],
    ) -> candle_core::Result<VisionOutput> {
        let rows: usize = grids.iter().map(|g| g[0] * g[1] * g[2]).sum();
        if pixels.dims() != [rows, self.cfg.patch_dim()] {
            candle_core::bail!(
                "pixel rows {:?} do not match the grids {grids:?} ({rows} x {})",
                pixels.dims(),
                self.cfg.patch_dim()
            );
        }
        let dtype = self.pos_embed.dtype();
        let mut xs = self.patch_embed.forward(&pixels.to_dtype(dtype)?)?;

        let mut pos = Vec::with_capacity(grids.len());
        let q = self.inv_freq.len();
        let mut cos = Vec::with_capacity(rows * 2 * q);
        let mut sin = Vec::with_capacity(rows * 2 * q);
        let mut segments = Vec::with_capacity(grids.len());
        for &[t, h, w] in grids {
            let p = self.frame_positions(h, w)?;
            pos.push(if t == 1 { p } else { p.repeat((t, 1))? });
            let order = self.block_order(h, w);
            for _ in 0..t {
                for &(r, c) in &order {
                    for axis in [r, c] {
                        for &f in &self.inv_freq {
                            let angle = axis as f32 * f;
                            cos.push(angle.cos());
                            sin.push(angle.sin());
                        }
                    }
                }
            }
            segments.push((t * h * w, t));
        }
        let pos = Tensor::cat(&pos, 0)?;
        xs = (xs + pos)?;
        let cos = Tensor::from_vec(cos, (rows, 2 * q), &self.device)?;
        let sin = Tensor::from_vec(sin, (rows, 2 * q), &self.device)?;

        let mut deepstack = vec![None; self.deepstack.len()];
        for (i, block) in self.blocks.iter().enumerate() {
            xs = block.forward(&xs, &segments, &cos, &sin)?;
            if let Some(j) = self.deepstack_at[i] {
                deepstack[j] = Some(self.deepstack[j].forward(&xs)?);
            }
        }
        let embeds = self.merger.forward(&xs)?;
        Ok(VisionOutput {
            embeds,
            deepstack: deepstack
                .into_iter()
                .map(|d| d.expect("every index is a block"))
                .collect(),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bilinear_taps_hit_the_table_corners() {
        // 4 samples from a side-4 table with align_corners: exactly the table entries.
        for (i, (taps, w)) in bilinear_taps(4, 4).into_iter().enumerate() {
            assert_eq!(taps[0], i);
            assert!((w[0] - 1.0).abs() < 1e-6 && w[1].abs() < 1e-6, "{w:?}");
        }
        // One sample sits on entry 0.
        let t = bilinear_taps(1, 4);
        assert_eq!((t[0].0[0], t[0].1[0]), (0, 1.0));
        // Midpoints split evenly.
        let t = bilinear_taps(3, 3);
        assert_eq!(t[1].0, [1, 2]);
        let t = bilinear_taps(5, 3);
        assert_eq!(t[1].0, [0, 1]);
        assert!((t[1].1[0] - 0.5).abs() < 1e-6 && (t[1].1[1] - 0.5).abs() < 1e-6);
    }
}
