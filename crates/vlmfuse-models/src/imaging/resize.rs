//! The resize kernels: torch's uint8 antialiased interpolation on `fast_image_resize`, Pillow's
//! in scalar fixed point. Both are separable (horizontal pass, round to uint8, vertical pass,
//! round), skip a pass whose size does not change (as both references do), and compute only
//! the columns and rows that survive the crop.

use fast_image_resize as fir;

use super::{center_crop_rgb8, Arith, Resample};
use crate::{FrameRef, ModelError};

fn filter(kind: Resample, arith: Arith, x: f64) -> f64 {
    let x = x.abs();
    match kind {
        Resample::Bilinear => {
            if x < 1.0 {
                1.0 - x
            } else {
                0.0
            }
        }
        Resample::Bicubic => {
            const A: f64 = -0.5;
            if x < 1.0 {
                ((A + 2.0) * x - (A + 3.0)) * x * x + 1.0
            } else if x < 2.0 {
                match arith {
                    // Pillow's `bicubic_filter`.
                    Arith::Pil => (((x - 5.0) * x + 8.0) * x - 4.0) * A,
                    // ATen's `cubic_convolution2`.
                    Arith::Torch => ((A * x - 5.0 * A) * x + 8.0 * A) * x - 4.0 * A,
                }
            } else {
                0.0
            }
        }
    }
}

/// Fixed-point weights of one axis: per output sample the first input index, the tap count and
/// `ksize` weights, scaled by `2^precision`.
struct AxisCoeffs {
    xmin: Vec<usize>,
    xsize: Vec<usize>,
    k: Vec<i64>,
    ksize: usize,
    precision: u32,
}

fn axis_coeffs(in_size: usize, out_size: usize, kind: Resample, arith: Arith) -> AxisCoeffs {
    let scale = in_size as f64 / out_size as f64;
    let half = match kind {
        Resample::Bilinear => 1.0,
        Resample::Bicubic => 2.0,
    };
    let (support, inv) = if scale >= 1.0 {
        (half * scale, 1.0 / scale)
    } else {
        (half, 1.0)
    };
    let ksize = support.ceil() as usize * 2 + 1;
    let mut xmin = Vec::with_capacity(out_size);
    let mut xsize = Vec::with_capacity(out_size);
    let mut w = vec![0f64; out_size * ksize];
    for i in 0..out_size {
        let center = scale * (i as f64 + 0.5);
        // C casts truncate toward zero; both references then clamp at 0.
        let lo = ((center - support + 0.5) as i64).max(0) as usize;
        let hi = ((center + support + 0.5) as i64).min(in_size as i64) as usize;
        let n = hi.saturating_sub(lo);
        let row = &mut w[i * ksize..(i + 1) * ksize];
        let mut total = 0.0;
        for (j, slot) in row.iter_mut().enumerate().take(n) {
            let v = filter(kind, arith, (j as f64 + lo as f64 - center + 0.5) * inv);
            *slot = v;
            total += v;
        }
        if total != 0.0 {
            row.iter_mut().take(n).for_each(|v| *v /= total);
        }
        xmin.push(lo);
        xsize.push(n);
    }
    let precision = match arith {
        // Pillow: PRECISION_BITS = 32 - 8 - 2.
        Arith::Pil => 22,
        // ATen: the largest precision whose rounded maximum weight still fits int16.
        Arith::Torch => {
            let wmax = w.iter().copied().fold(w[0], f64::max);
            let mut p = 0u32;
            while p < 22 {
                if (0.5 + wmax * (1i64 << (p + 1)) as f64) as i64 >= 1 << 15 {
                    break;
                }
                p += 1;
            }
            p
        }
    };
    let one = (1i64 << precision) as f64;
    let k = w
        .iter()
        .map(|&v| {
            if v < 0.0 {
                (-0.5 + v * one) as i64
            } else {
                (0.5 + v * one) as i64
            }
        })
        .collect();
    AxisCoeffs {
        xmin,
        xsize,
        k,
        ksize,
        precision,
    }
}

impl AxisCoeffs {
    /// One output sample from the input samples `at(i)`, i = the tap's input index.
    #[inline]
    fn sample(&self, o: usize, at: impl Fn(usize) -> [u8; 3]) -> [u8; 3] {
        let k = &self.k[o * self.ksize..o * self.ksize + self.xsize[o]];
        let mut acc = [1i64 << (self.precision - 1); 3];
        for (j, &kj) in k.iter().enumerate() {
            let p = at(self.xmin[o] + j);
            for c in 0..3 {
                acc[c] += p[c] as i64 * kj;
            }
        }
        acc.map(|a| (a >> self.precision).clamp(0, 255) as u8)
    }
}

/// Where the crop sits in the resized image.
#[derive(Clone, Copy)]
struct Geometry {
    /// The resized size.
    nw: usize,
    nh: usize,
    /// The crop: its top-left corner in the resized image and its size.
    left: usize,
    top: usize,
    cw: usize,
    ch: usize,
}

/// The scalar fixed-point kernel (Pillow's arithmetic in production; torch's too, as the
/// reference `fast_image_resize` is tested against).
fn scalar(
    frame: FrameRef,
    g: Geometry,
    kind: Resample,
    arith: Arith,
    tmp: &mut Vec<u8>,
    out: &mut Vec<u8>,
) {
    let (fw, fh) = (frame.width as usize, frame.height as usize);
    let rgb = frame.rgb;
    let px = |buf: &[u8], i: usize| [buf[i * 3], buf[i * 3 + 1], buf[i * 3 + 2]];
    // Horizontal pass over every row, the crop's columns only: `cw × fh`.
    let horiz: &[u8] = if g.nw != fw {
        let c = axis_coeffs(fw, g.nw, kind, arith);
        tmp.clear();
        tmp.reserve(g.cw * fh * 3);
        for y in 0..fh {
            let row = &rgb[y * fw * 3..(y + 1) * fw * 3];
            for xo in g.left..g.left + g.cw {
                tmp.extend_from_slice(&c.sample(xo, |x| px(row, x)));
            }
        }
        tmp
    } else if g.cw != fw {
        tmp.clear();
        for y in 0..fh {
            tmp.extend_from_slice(&rgb[(y * fw + g.left) * 3..(y * fw + g.left + g.cw) * 3]);
        }
        tmp
    } else {
        rgb
    };
    // Vertical pass, the crop's rows only.
    out.clear();
    if g.nh != fh {
        let c = axis_coeffs(fh, g.nh, kind, arith);
        out.reserve(g.cw * g.ch * 3);
        for yo in g.top..g.top + g.ch {
            for x in 0..g.cw {
                out.extend_from_slice(&c.sample(yo, |y| px(horiz, y * g.cw + x)));
            }
        }
    } else {
        out.extend_from_slice(&horiz[g.top * g.cw * 3..(g.top + g.ch) * g.cw * 3]);
    }
}

/// Reusable resize state: `fast_image_resize`'s resizer (its coefficient and row buffers) and
/// the intermediate images, so a batch of frames allocates once.
#[derive(Default)]
pub struct Resizer {
    fir: fir::Resizer,
    tmp: Vec<u8>,
    cols: Vec<u8>,
}

impl std::fmt::Debug for Resizer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Resizer").finish_non_exhaustive()
    }
}

impl Resizer {
    pub fn new() -> Self {
        Self::default()
    }

    /// `frame` resized to `resized` (`(w, h)`), then center-cropped to `crop` (zero-padded
    /// where the crop is larger, as transformers pads), into `out` as packed RGB8. Returns the
    /// output `(w, h)`.
    pub fn resize_crop(
        &mut self,
        frame: FrameRef,
        resized: (usize, usize),
        crop: Option<(usize, usize)>,
        kind: Resample,
        arith: Arith,
        out: &mut Vec<u8>,
    ) -> Result<(usize, usize), ModelError> {
        frame.validate()?;
        let (nw, nh) = resized;
        if nw == 0 || nh == 0 {
            return Err(ModelError::InvalidInput(format!("resize target {nw}x{nh}")));
        }
        let (cw, ch) = crop.unwrap_or((nw, nh));
        if cw == 0 || ch == 0 {
            return Err(ModelError::InvalidInput(format!("crop target {cw}x{ch}")));
        }
        if cw > nw || ch > nh {
            let mut full = Vec::new();
            self.resize_crop(frame, resized, None, kind, arith, &mut full)?;
            *out = center_crop_rgb8(&full, nw, nh, cw, ch);
            return Ok((cw, ch));
        }
        let g = Geometry {
            nw,
            nh,
            left: (nw - cw) / 2,
            top: (nh - ch) / 2,
            cw,
            ch,
        };
        match arith {
            Arith::Torch => self.torch(frame, g, kind, out)?,
            Arith::Pil => scalar(frame, g, kind, arith, &mut self.tmp, out),
        }
        Ok((cw, ch))
    }

    /// torch's kernel on `fast_image_resize` (same weights, precision and rounding). Each call
    /// resizes one direction only, horizontal first: one two-direction call would run the
    /// vertical pass first on u8 images and round at another point.
    fn torch(
        &mut self,
        frame: FrameRef,
        g: Geometry,
        kind: Resample,
        out: &mut Vec<u8>,
    ) -> Result<(), ModelError> {
        let (fw, fh) = (frame.width as usize, frame.height as usize);
        let err = |e: &dyn std::fmt::Display| {
            ModelError::InvalidInput(format!("resize {fw}x{fh} → {}x{}: {e}", g.nw, g.nh))
        };
        let alg = fir::ResizeAlg::Convolution(match kind {
            Resample::Bicubic => fir::FilterType::CatmullRom,
            Resample::Bilinear => fir::FilterType::Bilinear,
        });
        let opts = fir::ResizeOptions::new().resize_alg(alg);
        let u8x3 = fir::PixelType::U8x3;
        // Horizontal pass over every row to the full resized width: cropping inside the resizer
        // would shift the filter centres by float rounding.
        let horiz: &[u8] = if g.nw != fw {
            self.tmp.resize(g.nw * fh * 3, 0);
            let src = fir::images::ImageRef::new(fw as u32, fh as u32, frame.rgb, u8x3)
                .map_err(|e| err(&e))?;
            let mut dst =
                fir::images::Image::from_slice_u8(g.nw as u32, fh as u32, &mut self.tmp, u8x3)
                    .map_err(|e| err(&e))?;
            self.fir
                .resize(&src, &mut dst, &opts)
                .map_err(|e| err(&e))?;
            &self.tmp
        } else {
            frame.rgb
        };
        // The crop's columns (the vertical pass is per column).
        let cols: &[u8] = if g.cw != g.nw {
            self.cols.clear();
            for y in 0..fh {
                self.cols.extend_from_slice(
                    &horiz[(y * g.nw + g.left) * 3..(y * g.nw + g.left + g.cw) * 3],
                );
            }
            &self.cols
        } else {
            horiz
        };
        out.clear();
        if g.nh != fh {
            out.resize(g.cw * g.nh * 3, 0);
            let src = fir::images::ImageRef::new(g.cw as u32, fh as u32, cols, u8x3)
                .map_err(|e| err(&e))?;
            let mut dst = fir::images::Image::from_slice_u8(g.cw as u32, g.nh as u32, out, u8x3)
                .map_err(|e| err(&e))?;
            self.fir
                .resize(&src, &mut dst, &opts)
                .map_err(|e| err(&e))?;
            if g.ch != g.nh {
                out.drain(..g.top * g.cw * 3);
                out.truncate(g.ch * g.cw * 3);
            }
        } else {
            out.extend_from_slice(&cols[g.top * g.cw * 3..(g.top + g.ch) * g.cw * 3]);
        }
        Ok(())
    }
}

/// Resizes packed RGB8 to `out_w × out_h` with one reference's arithmetic.
pub fn resize_rgb8(
    frame: FrameRef,
    out_w: usize,
    out_h: usize,
    kind: Resample,
    arith: Arith,
) -> Result<Vec<u8>, ModelError> {
    let mut out = Vec::new();
    Resizer::new().resize_crop(frame, (out_w, out_h), None, kind, arith, &mut out)?;
    Ok(out)
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

    struct Rng(u64);
    impl Rng {
        fn next(&mut self) -> u64 {
            self.0 ^= self.0 << 13;
            self.0 ^= self.0 >> 7;
            self.0 ^= self.0 << 17;
            self.0
        }
        fn below(&mut self, n: u64) -> usize {
            (self.next() % n) as usize
        }
    }

    fn scalar_resize_crop(
        f: FrameRef,
        resized: (usize, usize),
        crop: (usize, usize),
        kind: Resample,
        arith: Arith,
    ) -> Vec<u8> {
        let g = Geometry {
            nw: resized.0,
            nh: resized.1,
            left: (resized.0 - crop.0) / 2,
            top: (resized.1 - crop.1) / 2,
            cw: crop.0,
            ch: crop.1,
        };
        let mut out = Vec::new();
        scalar(f, g, kind, arith, &mut Vec::new(), &mut out);
        out
    }

    /// The proof that `fast_image_resize` is torch's kernel: equal to the scalar transcription
    /// of ATen (weights, precision, rounding) on random sizes, up and down, both filters, with
    /// and without a crop, on noise (where any weight difference shows).
    #[test]
    fn fast_image_resize_is_torch_bit_for_bit() {
        let mut rng = Rng(0x5eed);
        let mut r = Resizer::new();
        let mut out = Vec::new();
        for case in 0..120 {
            let (w, h) = (1 + rng.below(90), 1 + rng.below(90));
            let (nw, nh) = (1 + rng.below(120), 1 + rng.below(120));
            let crop = if case % 3 == 0 {
                (1 + rng.below(nw as u64), 1 + rng.below(nh as u64))
            } else {
                (nw, nh)
            };
            let kind = if case % 2 == 0 {
                Resample::Bicubic
            } else {
                Resample::Bilinear
            };
            let rgb: Vec<u8> = (0..w * h * 3).map(|_| (rng.next() >> 13) as u8).collect();
            let f = FrameRef {
                width: w as u32,
                height: h as u32,
                rgb: &rgb,
            };
            let dims = r
                .resize_crop(f, (nw, nh), Some(crop), kind, Arith::Torch, &mut out)
                .unwrap();
            assert_eq!(dims, crop);
            let want = scalar_resize_crop(f, (nw, nh), crop, kind, Arith::Torch);
            assert!(
                out == want,
                "{kind:?} {w}x{h} -> {nw}x{nh} crop {crop:?}: {} values differ",
                out.iter().zip(&want).filter(|(a, b)| a != b).count()
            );
        }
    }

    #[test]
    fn cropping_equals_resizing_whole_then_cropping() {
        let mut rng = Rng(77);
        let mut r = Resizer::new();
        for case in 0..40 {
            let (w, h) = (2 + rng.below(70), 2 + rng.below(70));
            let (nw, nh) = (1 + rng.below(80), 1 + rng.below(80));
            let crop = (1 + rng.below(nw as u64), 1 + rng.below(nh as u64));
            let arith = if case % 2 == 0 {
                Arith::Torch
            } else {
                Arith::Pil
            };
            let rgb: Vec<u8> = (0..w * h * 3).map(|_| (rng.next() >> 13) as u8).collect();
            let f = FrameRef {
                width: w as u32,
                height: h as u32,
                rgb: &rgb,
            };
            let full = resize_rgb8(f, nw, nh, Resample::Bicubic, arith).unwrap();
            let want = center_crop_rgb8(&full, nw, nh, crop.0, crop.1);
            let mut got = Vec::new();
            r.resize_crop(f, (nw, nh), Some(crop), Resample::Bicubic, arith, &mut got)
                .unwrap();
            assert_eq!(got, want, "{arith:?} {w}x{h} -> {nw}x{nh} crop {crop:?}");
        }
        // A crop larger than the image pads.
        let rgb = frame(4, 4, |_, _, _| 9);
        let f = FrameRef {
            width: 4,
            height: 4,
            rgb: &rgb,
        };
        let mut got = Vec::new();
        let dims = r
            .resize_crop(
                f,
                (4, 4),
                Some((6, 4)),
                Resample::Bicubic,
                Arith::Pil,
                &mut got,
            )
            .unwrap();
        assert_eq!(dims, (6, 4));
        assert_eq!(&got[..3], &[0, 0, 0]);
        assert_eq!(&got[3..6], &[9, 9, 9]);
    }

    #[test]
    fn flat_colour_survives_both_resamplers_exactly() {
        let rgb = frame(37, 23, |_, _, c| [7u8, 128, 250][c]);
        let f = FrameRef {
            width: 37,
            height: 23,
            rgb: &rgb,
        };
        for arith in [Arith::Torch, Arith::Pil] {
            for kind in [Resample::Bicubic, Resample::Bilinear] {
                for (w, h) in [(16, 9), (80, 50), (37, 11), (7, 13)] {
                    let out = resize_rgb8(f, w, h, kind, arith).unwrap();
                    assert!(
                        out.chunks(3).all(|p| p == [7, 128, 250]),
                        "{arith:?} {kind:?} {w}x{h}"
                    );
                }
            }
        }
    }

    #[test]
    fn identity_resize_is_exact_and_bad_sizes_are_refused() {
        let rgb: Vec<u8> = (0..4 * 3 * 3).map(|i| (i * 7 % 256) as u8).collect();
        let f = FrameRef {
            width: 4,
            height: 3,
            rgb: &rgb,
        };
        for arith in [Arith::Torch, Arith::Pil] {
            assert_eq!(resize_rgb8(f, 4, 3, Resample::Bicubic, arith).unwrap(), rgb);
            assert!(resize_rgb8(f, 0, 3, Resample::Bicubic, arith).is_err());
        }
        let short = [0u8; 10];
        let bad = FrameRef {
            width: 2,
            height: 2,
            rgb: &short,
        };
        let e = resize_rgb8(bad, 1, 1, Resample::Bicubic, Arith::Torch).unwrap_err();
        assert_eq!(e.kind(), "invalid_input");
    }

    #[test]
    fn torch_precision_is_the_largest_that_fits_int16() {
        // Downscaling 4x spreads weights thin (max ≈ 0.14), so the precision exceeds 15 bits;
        // upscaling keeps a weight near 1 and the precision at 14.
        let c = axis_coeffs(64, 16, Resample::Bicubic, Arith::Torch);
        let wmax = c.k.iter().copied().max().unwrap();
        assert!(wmax < 1 << 15 && wmax * 2 >= (1 << 15) - 1, "{wmax}");
        let up = axis_coeffs(16, 64, Resample::Bicubic, Arith::Torch);
        assert_eq!(up.precision, 14);
        assert_eq!(
            axis_coeffs(16, 64, Resample::Bicubic, Arith::Pil).precision,
            22
        );
        // Weights of a sample sum to one in fixed point (up to rounding).
        for i in 0..16 {
            let s: i64 = c.k[i * c.ksize..(i + 1) * c.ksize].iter().sum();
            assert!((s - (1 << c.precision)).abs() <= c.ksize as i64, "{i}: {s}");
        }
    }

    #[test]
    fn downscale_is_antialiased() {
        // 1-pixel black/white stripes, 4x downscale: point sampling would give pure 0 or 255;
        // the widened filter must average them to mid-grey.
        let rgb = frame(64, 64, |x, _, _| if x % 2 == 0 { 0 } else { 255 });
        let f = FrameRef {
            width: 64,
            height: 64,
            rgb: &rgb,
        };
        for arith in [Arith::Torch, Arith::Pil] {
            let out = resize_rgb8(f, 16, 16, Resample::Bicubic, arith).unwrap();
            for row in out.chunks(16 * 3) {
                for &v in &row[6..14 * 3] {
                    assert!((v as f32 - 127.5).abs() < 3.0, "{arith:?}: pixel {v}");
                }
            }
        }
    }
}
