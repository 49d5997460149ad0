//! CLIP image preprocessing, reproducing `CLIPImageProcessor` (resize shortest edge, center crop,
//! rescale, normalise) so embeddings of real checkpoints match the ones they were trained with.
//!
//! Resampling is PIL's antialiased bicubic (a = -0.5, filter support widened by the downscale
//! factor), which is what `CLIPImageProcessor` uses (`resample=BICUBIC`). Unlike PIL it keeps the
//! intermediate pass in f32 instead of rounding to u8 (values still clamped to 0..=255 as PIL
//! does), so results differ from PIL by at most about one grey level.

use crate::{FrameRef, ModelError};

/// CLIP's per-channel normalisation constants (OpenAI CLIP training statistics), written with
/// the digits OpenAI published so they can be checked against the reference by eye.
#[allow(clippy::excessive_precision)]
pub const CLIP_MEAN: [f32; 3] = [0.481_454_66, 0.457_827_5, 0.408_210_73];
#[allow(clippy::excessive_precision)]
pub const CLIP_STD: [f32; 3] = [0.268_629_54, 0.261_302_58, 0.275_777_11];

/// Output size after "resize shortest edge to `size`", as transformers computes it
/// (`int(size * long / short)` for the long side).
pub fn resized_dims(width: u32, height: u32, size: usize) -> (usize, usize) {
    let (w, h) = (width as usize, height as usize);
    if w <= h {
        (size, (size as f64 * h as f64 / w as f64) as usize)
    } else {
        ((size as f64 * w as f64 / h as f64) as usize, size)
    }
}

fn bicubic(x: f64) -> f64 {
    const A: f64 = -0.5;
    let x = x.abs();
    if x < 1.0 {
        ((A + 2.0) * x - (A + 3.0)) * x * x + 1.0
    } else if x < 2.0 {
        (((x - 5.0) * x + 8.0) * x - 4.0) * A
    } else {
        0.0
    }
}

/// Per output sample: first input index and normalised weights (PIL's `precompute_coeffs`).
fn coeffs(in_size: usize, out_size: usize) -> Vec<(usize, Vec<f32>)> {
    let scale = in_size as f64 / out_size as f64;
    let filterscale = scale.max(1.0);
    let support = 2.0 * filterscale;
    (0..out_size)
        .map(|o| {
            let center = (o as f64 + 0.5) * scale;
            let xmin = ((center - support + 0.5).floor().max(0.0)) as usize;
            let xmax = ((center + support + 0.5).floor() as usize).min(in_size);
            let mut w: Vec<f64> = (xmin..xmax)
                .map(|x| bicubic((x as f64 - center + 0.5) / filterscale))
                .collect();
            let sum: f64 = w.iter().sum();
            if sum != 0.0 {
                w.iter_mut().for_each(|v| *v /= sum);
            }
            (xmin, w.into_iter().map(|v| v as f32).collect())
        })
        .collect()
}

/// Resize + center-crop + normalise one frame to a CHW `3 × size × size` buffer.
///
/// Only the rows/columns that survive the crop are resampled, so a 1080p frame costs about a
/// 224-wide strip, not a full resize.
pub fn clip_preprocess(frame: FrameRef, size: usize) -> Result<Vec<f32>, ModelError> {
    frame.validate()?;
    if size == 0 {
        return Err(ModelError::InvalidInput("preprocess size 0".into()));
    }
    let (in_w, in_h) = (frame.width as usize, frame.height as usize);
    let (new_w, new_h) = resized_dims(frame.width, frame.height, size);
    // transformers' center_crop: top = (h - crop) // 2.
    let left = (new_w - size) / 2;
    let top = (new_h - size) / 2;
    let cx = coeffs(in_w, new_w);
    let cy = coeffs(in_h, new_h);

    // Horizontal pass over every input row, kept columns only: tmp[y][x][c].
    let mut tmp = vec![0f32; in_h * size * 3];
    for y in 0..in_h {
        let row = &frame.rgb[y * in_w * 3..(y + 1) * in_w * 3];
        for (xo, (xmin, w)) in cx[left..left + size].iter().enumerate() {
            let mut acc = [0f32; 3];
            for (k, wk) in w.iter().enumerate() {
                let p = &row[(xmin + k) * 3..(xmin + k) * 3 + 3];
                acc[0] += wk * p[0] as f32;
                acc[1] += wk * p[1] as f32;
                acc[2] += wk * p[2] as f32;
            }
            let t = &mut tmp[(y * size + xo) * 3..(y * size + xo) * 3 + 3];
            for c in 0..3 {
                t[c] = acc[c].clamp(0.0, 255.0);
            }
        }
    }
    // Vertical pass, kept rows only, straight into normalised CHW.
    let mut out = vec![0f32; 3 * size * size];
    for (yo, (ymin, w)) in cy[top..top + size].iter().enumerate() {
        for xo in 0..size {
            let mut acc = [0f32; 3];
            for (k, wk) in w.iter().enumerate() {
                let t = &tmp[((ymin + k) * size + xo) * 3..((ymin + k) * size + xo) * 3 + 3];
                acc[0] += wk * t[0];
                acc[1] += wk * t[1];
                acc[2] += wk * t[2];
            }
            for c in 0..3 {
                let v = acc[c].clamp(0.0, 255.0) / 255.0;
                out[c * size * size + yo * size + xo] = (v - CLIP_MEAN[c]) / CLIP_STD[c];
            }
        }
    }
    Ok(out)
}

/// Resizes a whole frame to `out_w × out_h` with the same PIL-style antialiased bicubic as
/// [`clip_preprocess`], returning HWC floats in `0..=255`. Shared with the Qwen-VL video
/// preprocessing, which resizes without cropping and normalises with its own statistics.
pub fn resize_rgb(frame: FrameRef, out_w: usize, out_h: usize) -> Result<Vec<f32>, ModelError> {
    frame.validate()?;
    if out_w == 0 || out_h == 0 {
        return Err(ModelError::InvalidInput(format!(
            "resize target {out_w}x{out_h}"
        )));
    }
    let (in_w, in_h) = (frame.width as usize, frame.height as usize);
    let cx = coeffs(in_w, out_w);
    let cy = coeffs(in_h, out_h);
    let mut tmp = vec![0f32; in_h * out_w * 3];
    for y in 0..in_h {
        let row = &frame.rgb[y * in_w * 3..(y + 1) * in_w * 3];
        for (xo, (xmin, w)) in cx.iter().enumerate() {
            let mut acc = [0f32; 3];
            for (k, wk) in w.iter().enumerate() {
                let p = &row[(xmin + k) * 3..(xmin + k) * 3 + 3];
                acc[0] += wk * p[0] as f32;
                acc[1] += wk * p[1] as f32;
                acc[2] += wk * p[2] as f32;
            }
            let t = &mut tmp[(y * out_w + xo) * 3..(y * out_w + xo) * 3 + 3];
            for c in 0..3 {
                t[c] = acc[c].clamp(0.0, 255.0);
            }
        }
    }
    let mut out = vec![0f32; out_h * out_w * 3];
    for (yo, (ymin, w)) in cy.iter().enumerate() {
        for xo in 0..out_w {
            let mut acc = [0f32; 3];
            for (k, wk) in w.iter().enumerate() {
                let t = &tmp[((ymin + k) * out_w + xo) * 3..((ymin + k) * out_w + xo) * 3 + 3];
                acc[0] += wk * t[0];
                acc[1] += wk * t[1];
                acc[2] += wk * t[2];
            }
            let o = &mut out[(yo * out_w + xo) * 3..(yo * out_w + xo) * 3 + 3];
            for c in 0..3 {
                o[c] = acc[c].clamp(0.0, 255.0);
            }
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn norm(c: usize, v: u8) -> f32 {
        (v as f32 / 255.0 - CLIP_MEAN[c]) / CLIP_STD[c]
    }

    #[test]
    fn resize_keeps_flat_colour_and_identity() {
        let rgb: Vec<u8> = (0..6 * 4).flat_map(|_| [10u8, 128, 250]).collect();
        let f = FrameRef {
            width: 6,
            height: 4,
            rgb: &rgb,
        };
        let out = resize_rgb(f, 3, 2).unwrap();
        assert_eq!(out.len(), 3 * 2 * 3);
        for px in out.chunks_exact(3) {
            for (got, want) in px.iter().zip([10.0, 128.0, 250.0]) {
                assert!((got - want).abs() < 1e-3, "{got} vs {want}");
            }
        }
        let ramp: Vec<u8> = (0..6 * 4 * 3).map(|i| i as u8).collect();
        let f = FrameRef {
            width: 6,
            height: 4,
            rgb: &ramp,
        };
        let same = resize_rgb(f, 6, 4).unwrap();
        assert!(same
            .iter()
            .zip(&ramp)
            .all(|(a, &b)| (a - b as f32).abs() < 1e-3));
        assert!(resize_rgb(f, 0, 4).is_err());
    }

    #[test]
    fn dims_follow_transformers() {
        assert_eq!(resized_dims(1280, 720, 224), (398, 224));
        assert_eq!(resized_dims(720, 1280, 224), (224, 398));
        assert_eq!(resized_dims(300, 300, 224), (224, 224));
    }

    #[test]
    fn no_resize_needed_crops_center_and_normalises_exactly() {
        // 4 wide x 2 high, size 2: shortest side already 2, so only the crop (columns 1..3).
        let mut rgb = Vec::new();
        for y in 0..2u8 {
            for x in 0..4u8 {
                rgb.extend_from_slice(&[10 * x + y, 100 + x, 200 + y]);
            }
        }
        let f = FrameRef {
            width: 4,
            height: 2,
            rgb: &rgb,
        };
        let out = clip_preprocess(f, 2).unwrap();
        assert_eq!(out.len(), 12);
        for c in 0..3 {
            for y in 0..2usize {
                for xo in 0..2usize {
                    let x = xo + 1;
                    let src = rgb[(y * 4 + x) * 3 + c];
                    let got = out[c * 4 + y * 2 + xo];
                    assert!((got - norm(c, src)).abs() < 1e-6, "c{c} y{y} x{xo}: {got}");
                }
            }
        }
        // Spot-check one number by hand: R at (y=1, x=2) = 21 → (21/255 - 0.48145466)/0.26862954.
        assert!((out[2 + 1] - (-1.485_696)).abs() < 1e-4, "{}", out[3]);
    }

    #[test]
    fn constant_image_stays_constant_at_any_scale() {
        let (w, h) = (37u32, 23u32);
        let rgb: Vec<u8> = (0..w * h).flat_map(|_| [50u8, 128, 250]).collect();
        let out = clip_preprocess(
            FrameRef {
                width: w,
                height: h,
                rgb: &rgb,
            },
            16,
        )
        .unwrap();
        for c in 0..3 {
            let want = norm(c, [50, 128, 250][c]);
            for v in &out[c * 256..(c + 1) * 256] {
                assert!((v - want).abs() < 1e-4, "{v} vs {want}");
            }
        }
    }

    #[test]
    fn downscale_is_antialiased() {
        // 1-pixel black/white stripes, 4x downscale: point sampling would give pure 0 or 255;
        // the widened filter must average them to mid-grey.
        let (w, h) = (64u32, 64u32);
        let rgb: Vec<u8> = (0..h)
            .flat_map(|_| (0..w).flat_map(|x| if x % 2 == 0 { [0u8; 3] } else { [255u8; 3] }))
            .collect();
        let out = clip_preprocess(
            FrameRef {
                width: w,
                height: h,
                rgb: &rgb,
            },
            16,
        )
        .unwrap();
        for v in &out[16 * 2 + 2..16 * 2 + 14] {
            let px = (v * CLIP_STD[0] + CLIP_MEAN[0]) * 255.0;
            assert!((px - 127.5).abs() < 3.0, "pixel {px}");
        }
    }

    #[test]
    fn bad_buffer_is_an_error() {
        let rgb = [0u8; 10];
        let e = clip_preprocess(
            FrameRef {
                width: 2,
                height: 2,
                rgb: &rgb,
            },
            2,
        )
        .unwrap_err();
        assert_eq!(e.kind(), "invalid_input");
    }
}
