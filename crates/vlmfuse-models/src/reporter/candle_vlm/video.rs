//! Qwen-VL video preprocessing: frames → the flattened patch rows and `video_grid_thw` that the
//! vision tower expects. The patch order must match the HF processor exactly, because the vision
//! tower's position embeddings and 2×2 patch merger assume it; a different order still runs but
//! silently scrambles the image.

use crate::embed::preprocess::resize_rgb;
use crate::{FrameRef, ModelError};

/// Qwen2-VL's image statistics (the OpenAI CLIP values), the fallback when a checkpoint ships no
/// preprocessor config. Qwen3-VL checkpoints ship 0.5/0.5, which their config file supplies.
#[allow(clippy::excessive_precision)]
pub const QWEN_DEFAULT_MEAN: [f32; 3] = [0.481_454_66, 0.457_827_5, 0.408_210_73];
#[allow(clippy::excessive_precision)]
pub const QWEN_DEFAULT_STD: [f32; 3] = [0.268_629_54, 0.261_302_58, 0.275_777_11];

/// Geometry and statistics of the video processor.
#[derive(Debug, Clone, PartialEq)]
pub struct VideoProcessor {
    pub patch_size: usize,
    pub temporal_patch_size: usize,
    pub merge_size: usize,
    pub mean: [f32; 3],
    pub std: [f32; 3],
    /// Pixel budget per frame after resizing (the HF budget is per video and assumes hundreds of
    /// frames; here the frame count is small and fixed by config, so a per-frame budget is the
    /// knob that actually bounds the token count).
    pub min_pixels: usize,
    pub max_pixels: usize,
}

/// The vision tower's input for one clip.
#[derive(Debug, Clone)]
pub struct VideoPatches {
    /// Row-major `[t·h·w, C·temporal_patch_size·patch_size²]`.
    pub data: Vec<f32>,
    /// `[t, h, w]` in patches (not merged patches), as `video_grid_thw` wants it.
    pub grid_thw: [usize; 3],
    pub row_len: usize,
}

impl VideoPatches {
    /// Number of `<|video_pad|>` tokens: one per merged patch.
    pub fn merged_tokens(&self, merge_size: usize) -> usize {
        self.grid_thw[0] * self.grid_thw[1] * self.grid_thw[2] / (merge_size * merge_size)
    }
}

/// Python's `round` (half to even), so sizes match the HF processor on exact halves.
fn py_round(x: f64) -> f64 {
    x.round_ties_even()
}

/// Qwen's `smart_resize`: both sides a multiple of `factor`, the area within
/// `[min_pixels, max_pixels]`, aspect ratio kept as well as possible. Returns `(height, width)`.
pub fn smart_resize(
    height: usize,
    width: usize,
    factor: usize,
    min_pixels: usize,
    max_pixels: usize,
) -> Result<(usize, usize), ModelError> {
    if height == 0 || width == 0 || factor == 0 {
        return Err(ModelError::InvalidInput(format!(
            "cannot resize {width}x{height} to a multiple of {factor}"
        )));
    }
    let (h, w, f) = (height as f64, width as f64, factor as f64);
    if h.max(w) / h.min(w) > 200.0 {
        return Err(ModelError::InvalidInput(format!(
            "aspect ratio of {width}x{height} is above 200"
        )));
    }
    let mut h_bar = (py_round(h / f) * f).max(f);
    let mut w_bar = (py_round(w / f) * f).max(f);
    if h_bar * w_bar > max_pixels as f64 {
        let beta = (h * w / max_pixels as f64).sqrt();
        h_bar = ((h / beta / f).floor() * f).max(f);
        w_bar = ((w / beta / f).floor() * f).max(f);
    } else if h_bar * w_bar < min_pixels as f64 {
        let beta = (min_pixels as f64 / (h * w)).sqrt();
        h_bar = (h * beta / f).ceil() * f;
        w_bar = (w * beta / f).ceil() * f;
    }
    Ok((h_bar as usize, w_bar as usize))
}

impl VideoProcessor {
    /// Resizes, normalises and patchifies `frames` (all resized to the first frame's target
    /// size). An odd count is padded by repeating the last frame, as the HF processor does.
    pub fn process(&self, frames: &[FrameRef]) -> Result<VideoPatches, ModelError> {
        let first = frames
            .first()
            .ok_or_else(|| ModelError::InvalidInput("clip has no frames".into()))?;
        let (ps, tps, ms) = (self.patch_size, self.temporal_patch_size, self.merge_size);
        if ps == 0 || tps == 0 || ms == 0 {
            return Err(ModelError::BadConfig(
                "patch sizes of the video processor must be positive".into(),
            ));
        }
        let (rh, rw) = smart_resize(
            first.height as usize,
            first.width as usize,
            ps * ms,
            self.min_pixels,
            self.max_pixels,
        )?;
        // CHW, normalised, one buffer per frame.
        let mut planes: Vec<Vec<f32>> = Vec::with_capacity(frames.len() + 1);
        for f in frames {
            let hwc = resize_rgb(*f, rw, rh)?;
            let mut chw = vec![0f32; 3 * rh * rw];
            for (i, px) in hwc.chunks_exact(3).enumerate() {
                for c in 0..3 {
                    chw[c * rh * rw + i] = (px[c] / 255.0 - self.mean[c]) / self.std[c];
                }
            }
            planes.push(chw);
        }
        while !planes.len().is_multiple_of(tps) {
            let last = planes.last().expect("non-empty").clone();
            planes.push(last);
        }
        let (gt, gh, gw) = (planes.len() / tps, rh / ps, rw / ps);
        let row_len = 3 * tps * ps * ps;
        let mut data = Vec::with_capacity(gt * gh * gw * row_len);
        // Index order = HF's reshape (t, tps, C, h/ms, ms, ps, w/ms, ms, ps) transposed to
        // (t, h/ms, w/ms, ms, ms, C, tps, ps, ps).
        for t in 0..gt {
            for bh in 0..gh / ms {
                for bw in 0..gw / ms {
                    for mh in 0..ms {
                        for mw in 0..ms {
                            let y0 = (bh * ms + mh) * ps;
                            let x0 = (bw * ms + mw) * ps;
                            for c in 0..3 {
                                for tp in 0..tps {
                                    let plane = &planes[t * tps + tp][c * rh * rw..];
                                    for py in 0..ps {
                                        let row = &plane[(y0 + py) * rw + x0..];
                                        data.extend_from_slice(&row[..ps]);
                                    }
                                }
                            }
                        }
                    }
                }
            }
        }
        Ok(VideoPatches {
            data,
            grid_thw: [gt, gh, gw],
            row_len,
        })
    }
}

/// Picks `k` frame indices spread evenly over `n` (first and last included), so a clip sampled
/// densely by the media layer is thinned without bunching.
pub fn spread_indices(n: usize, k: usize) -> Vec<usize> {
    if k == 0 || n == 0 {
        return Vec::new();
    }
    if k >= n {
        return (0..n).collect();
    }
    if k == 1 {
        return vec![n / 2];
    }
    (0..k)
        .map(|i| ((i * (n - 1)) as f64 / (k - 1) as f64).round() as usize)
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::{Device, Tensor};

    #[test]
    fn smart_resize_matches_qwen_examples() {
        // Values from transformers' `smart_resize` (factor 28, Qwen2-VL defaults).
        assert_eq!(
            smart_resize(720, 1280, 28, 56 * 56, 28 * 28 * 1280).unwrap(),
            (728, 1288)
        );
        // Over budget: shrink, keeping multiples of the factor.
        let (h, w) = smart_resize(1080, 1920, 32, 1024, 640 * 360).unwrap();
        assert_eq!((h % 32, w % 32), (0, 0));
        assert!(h * w <= 640 * 360, "{h}x{w}");
        // Under budget: grow.
        let (h, w) = smart_resize(10, 10, 8, 256, 10_000).unwrap();
        assert!(h * w >= 256 && h % 8 == 0 && w % 8 == 0);
        // Python rounds halves to even: 20/8 = 2.5 -> 2.
        assert_eq!(smart_resize(20, 16, 8, 1, 10_000).unwrap(), (16, 16));
        assert!(smart_resize(1, 300, 8, 1, 10_000).is_err());
    }

    #[test]
    fn spread_is_even_and_bounded() {
        assert_eq!(spread_indices(10, 4), vec![0, 3, 6, 9]);
        assert_eq!(spread_indices(3, 8), vec![0, 1, 2]);
        assert_eq!(spread_indices(5, 1), vec![2]);
        assert!(spread_indices(0, 3).is_empty());
    }

    /// The loop order above against HF's reshape/transpose, done with candle's own permute.
    #[test]
    fn patch_layout_equals_hf_reshape_transpose() {
        let (w, h, n) = (16usize, 8usize, 3usize);
        let frames: Vec<Vec<u8>> = (0..n)
            .map(|k| {
                (0..w * h * 3)
                    .map(|i| ((i * 7 + k * 31) % 251) as u8)
                    .collect()
            })
            .collect();
        let refs: Vec<FrameRef> = frames
            .iter()
            .map(|rgb| FrameRef {
                width: w as u32,
                height: h as u32,
                rgb,
            })
            .collect();
        let vp = VideoProcessor {
            patch_size: 2,
            temporal_patch_size: 2,
            merge_size: 2,
            mean: [0.5; 3],
            std: [0.25; 3],
            min_pixels: 1,
            max_pixels: 1 << 20,
        };
        let out = vp.process(&refs).unwrap();
        // No resize happens (16x8 is a multiple of 4), 3 frames padded to 4.
        assert_eq!(out.grid_thw, [2, 4, 8]);
        assert_eq!(out.row_len, 3 * 2 * 2 * 2);
        assert_eq!(out.merged_tokens(2), 2 * 4 * 8 / 4);

        // Reference: (T, C, H, W) normalised, last frame repeated.
        let mut tchw = Vec::new();
        for k in [0, 1, 2, 2] {
            for c in 0..3 {
                for i in 0..h * w {
                    let v = frames[k][i * 3 + c] as f32 / 255.0;
                    tchw.push((v - 0.5) / 0.25);
                }
            }
        }
        let t = Tensor::from_vec(tchw, (4, 3, h, w), &Device::Cpu).unwrap();
        let (ps, tps, ms) = (2, 2, 2);
        let t = t
            .reshape(vec![2, tps, 3, h / ps / ms, ms, ps, w / ps / ms, ms, ps])
            .unwrap()
            .permute(vec![0, 3, 6, 4, 7, 2, 1, 5, 8])
            .unwrap()
            .contiguous()
            .unwrap()
            .flatten_all()
            .unwrap()
            .to_vec1::<f32>()
            .unwrap();
        assert_eq!(t.len(), out.data.len());
        for (i, (a, b)) in t.iter().zip(&out.data).enumerate() {
            assert!((a - b).abs() < 1e-5, "element {i}: {a} vs {b}");
        }
    }
}
