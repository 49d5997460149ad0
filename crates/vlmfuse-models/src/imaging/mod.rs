//! The one place that turns RGB frames into model pixels: resize kernels, center crop,
//! rescale-and-normalise, and the CLIP-style processor config that strings them together. Every
//! model's preprocessing (the CLIP embedders, Qwen3-VL's video processor, VideoLLaVA's image
//! and video processors) calls into here; none resamples on its own.
//!
//! Two reference behaviours are reproduced bit for bit, because checkpoints were trained on
//! them and the parity tests compare against them:
//!
//! - [`Arith::Torch`]: torch's native uint8 antialiased interpolation, which torchvision's
//!   `resize` runs on a uint8 tensor (transformers 5's fast image processors and every video
//!   processor): 16-bit fixed-point weights at the largest precision that fits, horizontal pass,
//!   round to uint8, vertical pass, round. `fast_image_resize` computes exactly this (the tests
//!   check it against a scalar transcription of ATen on random sizes), with SIMD, so it is the
//!   kernel here.
//! - [`Arith::Pil`]: Pillow's `Image.resize` (the slow image processors, e.g.
//!   `VideoLlavaImageProcessor`): the same separable passes with 22-bit fixed-point weights.
//!   `fast_image_resize` differs from it by a grey level on most images, so this one is a
//!   scalar kernel.
//!
//! Either way the image is resized whole and then cropped, as transformers does (mapping the
//! crop back onto the source moves the filter centres by float rounding and changes pixels);
//! each pass only computes the output rows or columns that survive the crop.

mod processor;
mod resize;

pub use processor::ImageProcessor;
pub use resize::{resize_rgb8, Resizer};

/// OpenAI CLIP's per-channel statistics, transformers' `OPENAI_CLIP_MEAN` / `OPENAI_CLIP_STD`,
/// with the digits OpenAI published.
#[allow(clippy::excessive_precision)]
pub const OPENAI_CLIP_MEAN: [f64; 3] = [0.48145466, 0.4578275, 0.40821073];
#[allow(clippy::excessive_precision)]
pub const OPENAI_CLIP_STD: [f64; 3] = [0.26862954, 0.26130258, 0.27577711];

/// The same in f32.
pub const CLIP_MEAN: [f32; 3] = [
    OPENAI_CLIP_MEAN[0] as f32,
    OPENAI_CLIP_MEAN[1] as f32,
    OPENAI_CLIP_MEAN[2] as f32,
];
pub const CLIP_STD: [f32; 3] = [
    OPENAI_CLIP_STD[0] as f32,
    OPENAI_CLIP_STD[1] as f32,
    OPENAI_CLIP_STD[2] as f32,
];

/// The resampling filter (PIL's numbering in configs: 2 = bilinear, 3 = bicubic).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Resample {
    Bilinear,
    /// Catmull-Rom, a = -0.5 (PIL `BICUBIC`, torch `bicubic`).
    Bicubic,
}

impl Resample {
    /// PIL's enum value as configs write it.
    pub fn from_pil(code: u64) -> Option<Self> {
        match code {
            2 => Some(Self::Bilinear),
            3 => Some(Self::Bicubic),
            _ => None,
        }
    }
}

/// Whose fixed-point resampling and float order of normalisation to reproduce.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Arith {
    /// torch on uint8 tensors; normalisation `(x - mean/r) / (std/r)` in f32, the fused
    /// rescale-and-normalise of transformers' torchvision processors.
    Torch,
    /// Pillow; rescale in f64, then `(x - mean) / std` in f32.
    Pil,
}

/// How a processor resizes before the crop.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ResizeTo {
    /// Shortest edge to this many pixels, aspect kept (transformers' `{"shortest_edge": n}`).
    ShortestEdge(u32),
    /// Exactly this size, aspect not kept (`{"height": h, "width": w}`).
    Exact { width: u32, height: u32 },
}

/// transformers' `get_resize_output_image_size(..., default_to_square=False)`: the short side
/// becomes `size`, the long side `int(size * long / short)`. Returns `(w, h)`.
pub fn shortest_edge_dims(width: usize, height: usize, size: usize) -> (usize, usize) {
    if width <= height {
        (size, (size as f64 * height as f64 / width as f64) as usize)
    } else {
        ((size as f64 * width as f64 / height as f64) as usize, size)
    }
}

/// Center crop of packed RGB8 to `cw × ch`, zero-padding first where the image is smaller
/// (transformers' `center_crop`: pad `(c - s) // 2` before, the rest after; top/left
/// `int((s - c) / 2)`).
pub fn center_crop_rgb8(img: &[u8], w: usize, h: usize, cw: usize, ch: usize) -> Vec<u8> {
    let (pl, pt) = (cw.saturating_sub(w) / 2, ch.saturating_sub(h) / 2);
    let (pw, ph) = (w.max(cw), h.max(ch));
    let padded: Vec<u8>;
    let src = if pw != w || ph != h {
        let mut p = vec![0u8; pw * ph * 3];
        for y in 0..h {
            p[((y + pt) * pw + pl) * 3..((y + pt) * pw + pl + w) * 3]
                .copy_from_slice(&img[y * w * 3..(y + 1) * w * 3]);
        }
        padded = p;
        &padded[..]
    } else {
        img
    };
    let top = (ph - ch) / 2;
    let left = (pw - cw) / 2;
    let mut out = Vec::with_capacity(cw * ch * 3);
    for y in top..top + ch {
        out.extend_from_slice(&src[(y * pw + left) * 3..(y * pw + left + cw) * 3]);
    }
    out
}

/// Rescale and normalise of uint8 values to model floats, in the float order of one reference.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Normalize {
    /// Multiplier from `u8` (`do_rescale`'s `rescale_factor`), or none.
    pub rescale: Option<f64>,
    pub mean: [f64; 3],
    pub std: [f64; 3],
    /// `do_normalize`: subtract `mean`, divide by `std`.
    pub normalize: bool,
    pub arith: Arith,
}

impl Normalize {
    /// Channel `c` of value `x`, exactly as the reference computes it.
    pub fn value(&self, c: usize, x: u8) -> f32 {
        let (m, s) = (self.mean[c], self.std[c]);
        let x = x as f32;
        match (self.arith, self.rescale, self.normalize) {
            (Arith::Torch, Some(r), true) => {
                // Fused: mean and std (f32) times 1/rescale in f32.
                let k = (1.0 / r) as f32;
                (x - m as f32 * k) / (s as f32 * k)
            }
            (Arith::Pil, Some(r), true) => ((x as f64 * r) as f32 - m as f32) / s as f32,
            (_, None, true) => (x - m as f32) / s as f32,
            (Arith::Torch, Some(r), false) => x * r as f32,
            (Arith::Pil, Some(r), false) => (x as f64 * r) as f32,
            (_, None, false) => x,
        }
    }

    /// Per-channel table `u8 → float`, so normalising costs one lookup per value.
    pub fn table(&self) -> [[f32; 256]; 3] {
        let mut t = [[0f32; 256]; 3];
        for (c, row) in t.iter_mut().enumerate() {
            for (v, out) in row.iter_mut().enumerate() {
                *out = self.value(c, v as u8);
            }
        }
        t
    }

    /// Packed RGB8 (HWC) into planar CHW floats; `out` holds `3 × pixels`.
    pub fn hwc_to_chw(table: &[[f32; 256]; 3], rgb: &[u8], out: &mut [f32]) {
        let plane = rgb.len() / 3;
        debug_assert_eq!(out.len(), 3 * plane);
        let (r, rest) = out.split_at_mut(plane);
        let (g, b) = rest.split_at_mut(plane);
        let [tr, tg, tb] = table;
        for (i, px) in rgb.chunks_exact(3).enumerate() {
            r[i] = tr[px[0] as usize];
            g[i] = tg[px[1] as usize];
            b[i] = tb[px[2] as usize];
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn frame(w: u32, h: u32, f: impl Fn(u32, u32, usize) -> u8) -> Vec<u8> {
        let mut v = Vec::with_capacity((w * h * 3) as usize);
        for y in 0..h {
            for x in 0..w {
                for c in 0..3 {
                    v.push(f(x, y, c));
                }
            }
        }
        v
    }

    #[test]
    fn clip_constants_are_the_published_digits() {
        #[allow(clippy::excessive_precision)]
        let (m, s) = (
            [0.481_454_66f32, 0.457_827_5, 0.408_210_73],
            [0.268_629_54f32, 0.261_302_58, 0.275_777_11],
        );
        assert_eq!(CLIP_MEAN, m);
        assert_eq!(CLIP_STD, s);
    }

    #[test]
    fn dims_follow_transformers() {
        assert_eq!(shortest_edge_dims(1280, 720, 224), (398, 224));
        assert_eq!(shortest_edge_dims(720, 1280, 224), (224, 398));
        assert_eq!(shortest_edge_dims(300, 300, 224), (224, 224));
    }

    #[test]
    fn crop_centres_and_pads_like_transformers() {
        let rgb = frame(5, 4, |x, y, _| (y * 10 + x) as u8);
        let c = center_crop_rgb8(&rgb, 5, 4, 3, 2);
        // top = int((4-2)/2) = 1, left = int((5-3)/2) = 1.
        let r: Vec<u8> = c.chunks(3).map(|p| p[0]).collect();
        assert_eq!(r, vec![11, 12, 13, 21, 22, 23]);
        // Larger crop: pad (6-5)//2 = 0 left, 1 right; (6-4)//2 = 1 top, 1 bottom.
        let c = center_crop_rgb8(&rgb, 5, 4, 6, 6);
        let r: Vec<u8> = c.chunks(3).map(|p| p[0]).collect();
        assert_eq!(&r[..6], &[0; 6]);
        assert_eq!(&r[6..12], &[0, 1, 2, 3, 4, 0]);
    }

    #[test]
    fn normalisation_orders() {
        for arith in [Arith::Torch, Arith::Pil] {
            let n = Normalize {
                rescale: Some(1.0 / 255.0),
                mean: OPENAI_CLIP_MEAN,
                std: OPENAI_CLIP_STD,
                normalize: true,
                arith,
            };
            let t = n.table();
            for c in 0..3 {
                for x in [0u8, 128, 255] {
                    let want = (x as f64 / 255.0 - OPENAI_CLIP_MEAN[c]) / OPENAI_CLIP_STD[c];
                    assert!((n.value(c, x) as f64 - want).abs() < 1e-5);
                    assert_eq!(t[c][x as usize], n.value(c, x));
                }
            }
        }
        // R at 21 → (21/255 - 0.48145466)/0.26862954, by hand.
        let n = Normalize {
            rescale: Some(1.0 / 255.0),
            mean: OPENAI_CLIP_MEAN,
            std: OPENAI_CLIP_STD,
            normalize: true,
            arith: Arith::Torch,
        };
        assert!((n.value(0, 21) - (-1.485_696)).abs() < 1e-4);
        let off = Normalize {
            normalize: false,
            ..n
        };
        assert_eq!(off.value(1, 255), 255.0 * (1.0f64 / 255.0) as f32);
    }
}
