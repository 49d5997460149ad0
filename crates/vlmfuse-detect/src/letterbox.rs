//! Letterbox preprocessing, exactly as ultralytics' predictor does it for a YOLO export.
//!
//! Why exact and not "a resize": a detector's boxes are only as good as the mapping between the
//! frame and the model input, and the parity test compares our input tensor with the
//! predictor's byte for byte. So this mirrors `ultralytics.data.augment.LetterBox` (scale, the
//! Python `round` of each side, centred padding split with the `±0.1` rounding trick, padding
//! value 114) and OpenCV's `cv2.resize(..., INTER_LINEAR)` on `u8` pixels, including its 11-bit
//! fixed-point coefficients and the rounding of its vectorised vertical pass (measured
//! bit-exact against opencv-python 5.1 on every size in the parity set).
//!
//! Frames arrive in RGB; ultralytics reads BGR and flips to RGB before the model. Letterboxing
//! treats the three channels alike, so doing it on RGB gives the same tensor.

use serde::Serialize;
use vlmfuse_core::{FrameError, FrameRef};

/// OpenCV's `INTER_RESIZE_COEF_BITS`: interpolation weights are integers out of 2048.
const COEF_SCALE: f32 = 2048.0;

/// The letterbox transform's settings (ultralytics' `LetterBox` arguments). The predictor uses
/// `auto = false` for fixed-shape exports, which is what [`Letterbox::new`] gives.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Letterbox {
    /// Model input height and width.
    pub height: u32,
    pub width: u32,
    /// Pad only up to a multiple of `stride` (dynamic-shape models), not to the full size.
    pub auto: bool,
    /// Stretch to the input size instead of keeping the aspect ratio.
    pub scale_fill: bool,
    /// Allow enlarging a frame smaller than the input.
    pub scaleup: bool,
    /// Centre the frame (pad both sides); otherwise pad right and bottom only.
    pub center: bool,
    pub stride: u32,
    pub pad_value: u8,
}

impl Letterbox {
    /// The predictor's transform for a fixed `height` x `width` input.
    pub fn new(height: u32, width: u32) -> Self {
        Self {
            height,
            width,
            auto: false,
            scale_fill: false,
            scaleup: true,
            center: true,
            stride: 32,
            pad_value: 114,
        }
    }

    /// Where a `frame_h` x `frame_w` frame lands in the input (ultralytics' `get_params`).
    pub fn geometry(&self, frame_h: u32, frame_w: u32) -> Geometry {
        let (nh, nw) = (self.height as f64, self.width as f64);
        let (h, w) = (frame_h as f64, frame_w as f64);
        let mut r = (nh / h).min(nw / w);
        if !self.scaleup {
            r = r.min(1.0);
        }
        let mut unpad_w = ((w * r).round_ties_even() as u32).max(1);
        let mut unpad_h = ((h * r).round_ties_even() as u32).max(1);
        let mut dw = self.width as f64 - unpad_w as f64;
        let mut dh = self.height as f64 - unpad_h as f64;
        if self.auto {
            dw = dw.rem_euclid(self.stride as f64);
            dh = dh.rem_euclid(self.stride as f64);
        } else if self.scale_fill {
            dw = 0.0;
            dh = 0.0;
            unpad_w = self.width;
            unpad_h = self.height;
        }
        if self.center {
            dw /= 2.0;
            dh /= 2.0;
        }
        let side = |v: f64| v.round_ties_even().max(0.0) as u32;
        Geometry {
            frame_h,
            frame_w,
            resized_h: unpad_h,
            resized_w: unpad_w,
            top: if self.center { side(dh - 0.1) } else { 0 },
            bottom: side(dh + 0.1),
            left: if self.center { side(dw - 0.1) } else { 0 },
            right: side(dw + 0.1),
        }
    }

    /// The letterboxed frame as RGB rows (`geometry.out_h() x geometry.out_w() x 3`).
    pub fn apply(&self, frame: FrameRef<'_>) -> Result<(Vec<u8>, Geometry), FrameError> {
        frame.validate()?;
        let g = self.geometry(frame.height, frame.width);
        let resized;
        let src: &[u8] = if (g.resized_w, g.resized_h) == (frame.width, frame.height) {
            frame.rgb
        } else {
            resized = resize_linear_u8(
                frame.rgb,
                frame.width as usize,
                frame.height as usize,
                g.resized_w as usize,
                g.resized_h as usize,
            );
            &resized
        };
        let (ow, oh) = (g.out_w() as usize, g.out_h() as usize);
        let mut out = vec![self.pad_value; ow * oh * 3];
        let (rw, rh) = (g.resized_w as usize, g.resized_h as usize);
        for y in 0..rh {
            let dst = ((y + g.top as usize) * ow + g.left as usize) * 3;
            out[dst..dst + rw * 3].copy_from_slice(&src[y * rw * 3..(y + 1) * rw * 3]);
        }
        Ok((out, g))
    }
}

/// Where a frame went inside the model input.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub struct Geometry {
    pub frame_h: u32,
    pub frame_w: u32,
    /// The frame's size after scaling, before padding.
    pub resized_h: u32,
    pub resized_w: u32,
    pub top: u32,
    pub bottom: u32,
    pub left: u32,
    pub right: u32,
}

impl Geometry {
    pub fn out_h(&self) -> u32 {
        self.resized_h + self.top + self.bottom
    }
    pub fn out_w(&self) -> u32 {
        self.resized_w + self.left + self.right
    }
}

/// RGB rows (`h x w x 3`, `u8`) to the model's `[3, h, w]` `f32` planes in `[0, 1]`, written
/// into `out` (`3 * h * w` values): the predictor's `permute` and `div_(255)`.
pub fn to_chw(rgb: &[u8], h: usize, w: usize, out: &mut [f32]) {
    let plane = h * w;
    debug_assert_eq!(rgb.len(), plane * 3);
    debug_assert_eq!(out.len(), plane * 3);
    // `v / 255` exactly as torch computes it, looked up (a division per value is slow).
    let lut: [f32; 256] = std::array::from_fn(|v| v as f32 / 255.0);
    let (r, rest) = out.split_at_mut(plane);
    let (g, b) = rest.split_at_mut(plane);
    for (i, px) in rgb.chunks_exact(3).enumerate() {
        r[i] = lut[px[0] as usize];
        g[i] = lut[px[1] as usize];
        b[i] = lut[px[2] as usize];
    }
}

/// Horizontal (or vertical) taps of OpenCV's linear resize: source offset and the two
/// fixed-point weights per destination index, and the first index from which the right
/// neighbour falls outside (OpenCV's `xmax`: from there on the edge pixel is used alone).
fn linear_taps(src: usize, dst: usize) -> (Vec<usize>, Vec<[i32; 2]>, usize) {
    // OpenCV computes the scale as 1 / (dst / src), not src / dst; the two can differ in the
    // last bit, which moves a tap.
    let scale = 1.0 / (dst as f64 / src as f64);
    let mut ofs = Vec::with_capacity(dst);
    let mut a = Vec::with_capacity(dst);
    let mut xmax = dst;
    for d in 0..dst {
        let f = ((d as f64 + 0.5) * scale - 0.5) as f32;
        let mut s = f.floor() as i64;
        let mut f = f - s as f32;
        if s < 0 {
            f = 0.0;
            s = 0;
        }
        if s + 1 >= src as i64 {
            xmax = xmax.min(d);
            if s >= src as i64 - 1 {
                f = 0.0;
                s = src as i64 - 1;
            }
        }
        ofs.push(s as usize);
        a.push([
            round_half_even((1.0 - f) * COEF_SCALE),
            round_half_even(f * COEF_SCALE),
        ]);
    }
    (ofs, a, xmax)
}

/// OpenCV's `saturate_cast<short>(float)` (`cvRound`: round half to even).
fn round_half_even(v: f32) -> i32 {
    v.round_ties_even() as i32
}

/// `cv2.resize(src, (dw, dh), interpolation=cv2.INTER_LINEAR)` on packed RGB `u8` rows.
///
/// The horizontal pass is exact integer arithmetic (weights out of 2048); the vertical pass
/// reproduces OpenCV's SIMD kernel (`VResizeLinearVec_32s8u`): each row sum is shifted right by
/// 4, multiplied by its 11-bit weight keeping the high 16 bits, and the two halves are added
/// and rounded with `+2 >> 2`. This truncates differently from the scalar formula
/// (`(a + b + 2^21) >> 22`), by one grey level on ~10 % of pixels, and it is what runs on every
/// x86 build of OpenCV.
pub fn resize_linear_u8(src: &[u8], sw: usize, sh: usize, dw: usize, dh: usize) -> Vec<u8> {
    const CN: usize = 3;
    let (xo, xa, xmax) = linear_taps(sw, dw);
    // Per destination column: the two source byte offsets and weights. Past `xmax` OpenCV
    // takes the edge pixel times 2048, which is the same as both taps on it with (2048, 0).
    let taps: Vec<(usize, usize, i32, i32)> = (0..dw)
        .map(|dx| {
            let s0 = xo[dx] * CN;
            if dx < xmax {
                (s0, s0 + CN, xa[dx][0], xa[dx][1])
            } else {
                (s0, s0, COEF_SCALE as i32, 0)
            }
        })
        .collect();
    let hresize = |sy: usize, out: &mut [i32]| {
        let row = &src[sy * sw * CN..(sy + 1) * sw * CN];
        for (o, &(s0, s1, a0, a1)) in out.chunks_exact_mut(CN).zip(&taps) {
            for c in 0..CN {
                o[c] = row[s0 + c] as i32 * a0 + row[s1 + c] as i32 * a1;
            }
        }
    };
    // Vertical taps are not clamped like the horizontal ones: OpenCV clamps the source rows
    // but keeps the weights (so the first rows of an upscale use the first source row twice).
    let scale_y = 1.0 / (dh as f64 / sh as f64);
    // The two horizontally resized source rows in use; rows only move down, so each source
    // row is resized once.
    let mut rows = [vec![0i32; dw * CN], vec![0i32; dw * CN]];
    let mut have = [usize::MAX; 2];
    let mut dst = vec![0u8; dw * dh * CN];
    for (dy, out) in dst.chunks_exact_mut(dw * CN).enumerate() {
        let fy = ((dy as f64 + 0.5) * scale_y - 0.5) as f32;
        let sy = fy.floor() as i64;
        let fy = fy - sy as f32;
        let b0 = round_half_even((1.0 - fy) * COEF_SCALE);
        let b1 = round_half_even(fy * COEF_SCALE);
        let r0 = sy.clamp(0, sh as i64 - 1) as usize;
        let r1 = (sy + 1).clamp(0, sh as i64 - 1) as usize;
        if have[0] != r0 {
            if have[1] == r0 {
                rows.swap(0, 1);
                have.swap(0, 1);
            } else {
                hresize(r0, &mut rows[0]);
                have[0] = r0;
            }
        }
        if have[1] != r1 {
            hresize(r1, &mut rows[1]);
            have[1] = r1;
        }
        for ((o, &a), &b) in out.iter_mut().zip(&rows[0]).zip(&rows[1]) {
            let v = (((a >> 4) * b0) >> 16) + (((b >> 4) * b1) >> 16) + 2;
            *o = (v >> 2).clamp(0, 255) as u8;
        }
    }
    dst
}

#[cfg(test)]
mod tests {
    use super::*;

    fn geometry(h: u32, w: u32) -> Geometry {
        Letterbox::new(160, 160).geometry(h, w)
    }

    #[test]
    fn landscape_frames_are_padded_top_and_bottom_with_python_rounding() {
        // 320x180 -> 160x90, 70 px of padding split 35/35.
        let g = geometry(180, 320);
        assert_eq!(
            (g.resized_w, g.resized_h, g.top, g.bottom, g.left, g.right),
            (160, 90, 35, 35, 0, 0)
        );
        // 97x61 -> r = 160/97, 61 r = 100.62 -> 101; 59 px split 29/30 by the -0.1/+0.1 rule.
        let g = geometry(61, 97);
        assert_eq!(
            (g.resized_w, g.resized_h, g.top, g.bottom),
            (160, 101, 29, 30)
        );
        assert_eq!((g.out_w(), g.out_h()), (160, 160));
    }

    #[test]
    fn a_frame_of_the_input_size_is_copied_untouched() {
        let rgb: Vec<u8> = (0..160 * 160 * 3).map(|i| (i % 251) as u8).collect();
        let f = FrameRef {
            width: 160,
            height: 160,
            rgb: &rgb,
        };
        let (out, g) = Letterbox::new(160, 160).apply(f).unwrap();
        assert_eq!(out, rgb);
        assert_eq!((g.top, g.left), (0, 0));
    }

    #[test]
    fn padding_is_114_and_a_bad_buffer_is_an_error() {
        let rgb = vec![0u8; 4 * 2 * 3];
        let f = FrameRef {
            width: 4,
            height: 2,
            rgb: &rgb,
        };
        let (out, g) = Letterbox::new(8, 8).apply(f).unwrap();
        assert_eq!((g.resized_w, g.resized_h, g.top, g.bottom), (8, 4, 2, 2));
        assert!(out[..8 * 2 * 3].iter().all(|&v| v == 114));
        assert!(out[8 * 2 * 3..8 * 6 * 3].iter().all(|&v| v == 0));
        let short = FrameRef {
            width: 4,
            height: 2,
            rgb: &rgb[1..],
        };
        assert!(Letterbox::new(8, 8).apply(short).is_err());
    }

    #[test]
    fn resizing_a_flat_image_keeps_it_flat_and_a_ramp_monotone() {
        let flat = vec![77u8; 13 * 7 * 3];
        assert!(resize_linear_u8(&flat, 13, 7, 40, 21)
            .iter()
            .all(|&v| v == 77));
        let ramp: Vec<u8> = (0..50).flat_map(|x| [x as u8 * 5; 3]).collect();
        let up = resize_linear_u8(&ramp, 50, 1, 173, 1);
        assert!(up
            .chunks(3)
            .zip(up.chunks(3).skip(1))
            .all(|(a, b)| a[0] <= b[0]));
        assert_eq!((up[0], up[up.len() - 1]), (0, 245));
    }
}
