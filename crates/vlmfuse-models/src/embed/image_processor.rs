//! `CLIPImageProcessor` as a checkpoint's `preprocessor_config.json` describes it (resize the
//! shortest edge, center-crop, rescale, normalise), fast enough that preparing frames never
//! dominates an embed.
//!
//! Why this and not [`super::preprocess::clip_preprocess`]: that one hard-codes the OpenAI CLIP
//! statistics and a square crop equal to the resize, and resamples in scalar f32 (within about
//! one grey level of PIL on smooth images, a few on sharp noise). Here the resampling is
//! `fast_image_resize`'s SIMD convolution on `u8` pixels, run as PIL runs it (horizontal pass,
//! round to `u8`, vertical pass, round): the pixels equal what transformers' `CLIPImageProcessor`
//! (PIL) makes, to float rounding (the tests check it against its output), at a fraction of the
//! cost. The crop is mapped back onto the source, so only the pixels that survive it are
//! resampled, and normalisation is a 256-entry table per channel.

use std::num::NonZeroUsize;

use fast_image_resize as fir;
use serde_json::Value;

use super::preprocess::{resized_dims, CLIP_MEAN, CLIP_STD};
use crate::{FrameRef, ModelError};

/// How frames are resized before the crop.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ResizeTo {
    /// Shortest edge to this many pixels, aspect kept (transformers' `{"shortest_edge": n}`).
    ShortestEdge(u32),
    /// Exactly this size, aspect not kept (`{"height": h, "width": w}`).
    Exact { width: u32, height: u32 },
}

/// PIL's resampling filters that CLIP-style processors use (`resample` 3 and 2).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Resample {
    /// PIL `BICUBIC` (Catmull-Rom, a = -0.5), CLIP's choice.
    Bicubic,
    /// PIL `BILINEAR`.
    Bilinear,
}

/// The preprocessing of one model: frame → normalised CHW floats.
#[derive(Debug, Clone, PartialEq)]
pub struct ImageProcessor {
    pub resize: Option<ResizeTo>,
    pub resample: Resample,
    /// Center crop `(width, height)` after the resize.
    pub crop: Option<(u32, u32)>,
    /// Multiplier from `u8` to the model's range (1/255 unless `do_rescale` is false).
    pub rescale: f32,
    /// Per-channel mean and std (0 and 1 when `do_normalize` is false).
    pub mean: [f32; 3],
    pub std: [f32; 3],
}

impl ImageProcessor {
    /// OpenAI CLIP's processor for a square input of `size` (transformers' defaults).
    pub fn clip(size: u32) -> Self {
        Self {
            resize: Some(ResizeTo::ShortestEdge(size)),
            resample: Resample::Bicubic,
            crop: Some((size, size)),
            rescale: 1.0 / 255.0,
            mean: CLIP_MEAN,
            std: CLIP_STD,
        }
    }

    /// Reads a `preprocessor_config.json` (CLIPImageProcessor / CLIPFeatureExtractor layout).
    /// A field that is absent means what it means to transformers (its defaults are CLIP's).
    pub fn from_preprocessor_config(v: &Value) -> Result<Self, ModelError> {
        let bad = |m: String| ModelError::BadConfig(format!("preprocessor_config.json: {m}"));
        let flag = |k: &str| -> Result<bool, ModelError> {
            match v.get(k) {
                None | Some(Value::Null) => Ok(true),
                Some(Value::Bool(b)) => Ok(*b),
                Some(o) => Err(bad(format!("`{k}` must be true or false, got {o}"))),
            }
        };
        let resize = if flag("do_resize")? {
            Some(match v.get("size") {
                None | Some(Value::Null) => ResizeTo::ShortestEdge(224),
                Some(s) => parse_size(s, true).map_err(|m| bad(format!("`size`: {m}")))?,
            })
        } else {
            None
        };
        let crop = if flag("do_center_crop")? {
            Some(match v.get("crop_size") {
                None | Some(Value::Null) => (224, 224),
                Some(s) => {
                    match parse_size(s, false).map_err(|m| bad(format!("`crop_size`: {m}")))? {
                        ResizeTo::Exact { width, height } => (width, height),
                        ResizeTo::ShortestEdge(n) => (n, n),
                    }
                }
            })
        } else {
            None
        };
        let resample = match v.get("resample").and_then(Value::as_u64) {
            None | Some(3) => Resample::Bicubic,
            Some(2) => Resample::Bilinear,
            Some(r) => {
                return Err(bad(format!(
                    "`resample` {r} is not supported (2 = bilinear, 3 = bicubic)"
                )))
            }
        };
        let rescale = if flag("do_rescale")? {
            match v.get("rescale_factor") {
                None | Some(Value::Null) => 1.0 / 255.0,
                Some(f) => f
                    .as_f64()
                    .filter(|f| f.is_finite() && *f > 0.0)
                    .ok_or_else(|| bad(format!("`rescale_factor` {f} is not a positive number")))?
                    as f32,
            }
        } else {
            1.0
        };
        let (mean, std) = if flag("do_normalize")? {
            (
                triple(v, "image_mean", CLIP_MEAN).map_err(bad)?,
                triple(v, "image_std", CLIP_STD).map_err(bad)?,
            )
        } else {
            ([0.0; 3], [1.0; 3])
        };
        if std.iter().any(|s| *s == 0.0 || !s.is_finite()) {
            return Err(bad(format!(
                "`image_std` {std:?} has a zero or non-finite entry"
            )));
        }
        let p = Self {
            resize,
            resample,
            crop,
            rescale,
            mean,
            std,
        };
        p.check()?;
        Ok(p)
    }

    fn check(&self) -> Result<(), ModelError> {
        let bad = |m: String| ModelError::BadConfig(format!("preprocessor_config.json: {m}"));
        match self.resize {
            Some(ResizeTo::ShortestEdge(0)) | Some(ResizeTo::Exact { width: 0, .. }) => {
                return Err(bad("resize to 0 pixels".into()))
            }
            Some(ResizeTo::Exact { height: 0, .. }) => {
                return Err(bad("resize to 0 pixels".into()))
            }
            _ => {}
        }
        if let Some((w, h)) = self.crop {
            if w == 0 || h == 0 {
                return Err(bad("crop to 0 pixels".into()));
            }
            // transformers pads when the crop is larger than the resized frame; no CLIP
            // checkpoint is configured that way, so refuse instead of inventing padding.
            let fits = match self.resize {
                Some(ResizeTo::ShortestEdge(s)) => w <= s && h <= s,
                Some(ResizeTo::Exact { width, height }) => w <= width && h <= height,
                None => true,
            };
            if !fits {
                return Err(bad(format!(
                    "crop {w}x{h} is larger than the resize {:?}",
                    self.resize
                )));
            }
        }
        Ok(())
    }

    /// `(width, height)` of the model input this produces from a `w × h` frame.
    pub fn output_size(&self, w: u32, h: u32) -> (u32, u32) {
        if let Some(c) = self.crop {
            return c;
        }
        self.resized(w, h)
    }

    /// The output size when it does not depend on the frame (there is a crop or an exact
    /// resize), which is what a fixed-size model input needs.
    pub fn fixed_output_size(&self) -> Option<(u32, u32)> {
        match (self.crop, self.resize) {
            (Some(c), _) => Some(c),
            (None, Some(ResizeTo::Exact { width, height })) => Some((width, height)),
            _ => None,
        }
    }

    fn resized(&self, w: u32, h: u32) -> (u32, u32) {
        match self.resize {
            Some(ResizeTo::ShortestEdge(s)) => {
                let (nw, nh) = resized_dims(w, h, s as usize);
                (nw as u32, nh as u32)
            }
            Some(ResizeTo::Exact { width, height }) => (width, height),
            None => (w, h),
        }
    }

    fn filter(&self) -> fir::FilterType {
        match self.resample {
            Resample::Bicubic => fir::FilterType::CatmullRom,
            Resample::Bilinear => fir::FilterType::Bilinear,
        }
    }

    /// Per-channel table `u8 → normalised float`, so normalisation costs one lookup per value.
    fn table(&self) -> [[f32; 256]; 3] {
        let mut t = [[0f32; 256]; 3];
        for (c, row) in t.iter_mut().enumerate() {
            for (v, out) in row.iter_mut().enumerate() {
                *out = (v as f32 * self.rescale - self.mean[c]) / self.std[c];
            }
        }
        t
    }

    /// One frame into `out` (CHW, `3 × height × width` of [`output_size`](Self::output_size)).
    pub fn process_into(&self, frame: FrameRef, out: &mut [f32]) -> Result<(), ModelError> {
        Worker::new(self).process_into(frame, out)
    }

    /// All frames into one `[n, 3, H, W]` buffer, split over up to `threads` threads (frames are
    /// independent, so this is the one place where preprocessing uses more than one core).
    /// Every frame must give the same output size.
    pub fn process_batch(
        &self,
        frames: &[FrameRef],
        threads: NonZeroUsize,
    ) -> Result<(Vec<f32>, (u32, u32)), ModelError> {
        let Some(first) = frames.first() else {
            return Err(ModelError::InvalidInput("no frames to preprocess".into()));
        };
        for f in frames {
            f.validate()?;
        }
        let (w, h) = self.output_size(first.width, first.height);
        if let Some(f) = frames
            .iter()
            .find(|f| self.output_size(f.width, f.height) != (w, h))
        {
            return Err(ModelError::InvalidInput(format!(
                "frames of different sizes ({}x{} and {}x{}) without a crop to one size",
                first.width, first.height, f.width, f.height
            )));
        }
        let per = 3 * w as usize * h as usize;
        let mut buf = vec![0f32; per * frames.len()];
        let threads = threads.get().min(frames.len());
        if threads <= 1 {
            let mut worker = Worker::new(self);
            for (f, out) in frames.iter().zip(buf.chunks_exact_mut(per)) {
                worker.process_into(*f, out)?;
            }
        } else {
            let chunk = frames.len().div_ceil(threads);
            std::thread::scope(|s| {
                let handles: Vec<_> = frames
                    .chunks(chunk)
                    .zip(buf.chunks_mut(chunk * per))
                    .map(|(fs, outs)| {
                        s.spawn(move || {
                            let mut worker = Worker::new(self);
                            for (f, out) in fs.iter().zip(outs.chunks_exact_mut(per)) {
                                worker.process_into(*f, out)?;
                            }
                            Ok::<(), ModelError>(())
                        })
                    })
                    .collect();
                handles.into_iter().try_for_each(|h| {
                    h.join().unwrap_or_else(|_| {
                        Err(ModelError::InvalidInput(
                            "preprocessing thread panicked".into(),
                        ))
                    })
                })
            })?;
        }
        Ok((buf, (w, h)))
    }
}

/// Per-thread state: the resizer keeps its scratch buffers between frames.
struct Worker<'a> {
    p: &'a ImageProcessor,
    resizer: fir::Resizer,
    table: [[f32; 256]; 3],
    /// After the horizontal pass: `crop width × frame height`.
    tmp: Vec<u8>,
    rgb: Vec<u8>,
}

impl<'a> Worker<'a> {
    fn new(p: &'a ImageProcessor) -> Self {
        Self {
            p,
            resizer: fir::Resizer::new(),
            table: p.table(),
            tmp: Vec::new(),
            rgb: Vec::new(),
        }
    }

    fn process_into(&mut self, frame: FrameRef, out: &mut [f32]) -> Result<(), ModelError> {
        frame.validate()?;
        let (fw, fh) = (frame.width, frame.height);
        let (nw, nh) = self.p.resized(fw, fh);
        let (cw, ch) = self.p.crop.unwrap_or((nw, nh));
        if cw > nw || ch > nh {
            return Err(ModelError::InvalidInput(format!(
                "frame {fw}x{fh} is smaller than the {cw}x{ch} crop"
            )));
        }
        let want = 3 * cw as usize * ch as usize;
        if out.len() != want {
            return Err(ModelError::InvalidInput(format!(
                "output buffer holds {} floats, {cw}x{ch} needs {want}",
                out.len()
            )));
        }
        // transformers' center_crop: top = (h - crop) // 2, in the resized frame. Mapped back
        // onto the source so that only the kept region is resampled; the filter taps still read
        // the pixels around it, as a full resize followed by a crop would.
        let (left, top) = ((nw - cw) / 2, (nh - ch) / 2);
        let sx = fw as f64 / nw as f64;
        let sy = fh as f64 / nh as f64;
        // Two single-direction passes, horizontal first, each rounding to u8: PIL's order. (One
        // two-pass call would run the vertical pass first for u8 images, which rounds and clamps
        // bicubic overshoot at another point and drifts by a few grey levels on sharp detail.)
        let src = fir::images::ImageRef::new(fw, fh, frame.rgb, fir::PixelType::U8x3)
            .map_err(|e| ModelError::InvalidInput(format!("frame buffer: {e}")))?;
        let alg = fir::ResizeAlg::Convolution(self.p.filter());
        let resize_err = |e: fir::ResizeError| {
            ModelError::InvalidInput(format!("resize {fw}x{fh} → {cw}x{ch}: {e}"))
        };
        self.tmp.resize(cw as usize * fh as usize * 3, 0);
        let mut tmp =
            fir::images::Image::from_slice_u8(cw, fh, &mut self.tmp, fir::PixelType::U8x3)
                .map_err(|e| ModelError::InvalidInput(format!("resize buffer: {e}")))?;
        let horizontal = fir::ResizeOptions::new().resize_alg(alg).crop(
            left as f64 * sx,
            0.0,
            cw as f64 * sx,
            fh as f64,
        );
        self.resizer
            .resize(&src, &mut tmp, &horizontal)
            .map_err(resize_err)?;
        self.rgb.resize(want, 0);
        let mut dst =
            fir::images::Image::from_slice_u8(cw, ch, &mut self.rgb, fir::PixelType::U8x3)
                .map_err(|e| ModelError::InvalidInput(format!("resize buffer: {e}")))?;
        let vertical = fir::ResizeOptions::new().resize_alg(alg).crop(
            0.0,
            top as f64 * sy,
            cw as f64,
            ch as f64 * sy,
        );
        self.resizer
            .resize(&tmp, &mut dst, &vertical)
            .map_err(resize_err)?;
        // HWC u8 → CHW normalised floats.
        let plane = cw as usize * ch as usize;
        let (r, rest) = out.split_at_mut(plane);
        let (g, b) = rest.split_at_mut(plane);
        let [tr, tg, tb] = &self.table;
        for (i, px) in self.rgb.chunks_exact(3).enumerate() {
            r[i] = tr[px[0] as usize];
            g[i] = tg[px[1] as usize];
            b[i] = tb[px[2] as usize];
        }
        Ok(())
    }
}

fn parse_size(s: &Value, shortest_ok: bool) -> Result<ResizeTo, String> {
    let px = |v: &Value| -> Result<u32, String> {
        v.as_u64()
            .filter(|n| *n > 0 && *n <= 16384)
            .map(|n| n as u32)
            .ok_or_else(|| format!("{v} is not a pixel count"))
    };
    match s {
        Value::Number(_) => px(s).map(|n| {
            if shortest_ok {
                ResizeTo::ShortestEdge(n)
            } else {
                ResizeTo::Exact {
                    width: n,
                    height: n,
                }
            }
        }),
        Value::Object(o) => {
            if let Some(n) = o.get("shortest_edge") {
                if o.contains_key("longest_edge") {
                    return Err("`longest_edge` is not supported".into());
                }
                return px(n).map(ResizeTo::ShortestEdge);
            }
            match (o.get("height"), o.get("width")) {
                (Some(h), Some(w)) => Ok(ResizeTo::Exact {
                    width: px(w)?,
                    height: px(h)?,
                }),
                _ => Err(format!(
                    "{s} has neither `shortest_edge` nor `height` + `width`"
                )),
            }
        }
        other => Err(format!("{other} is neither a number nor an object")),
    }
}

fn triple(v: &Value, key: &str, default: [f32; 3]) -> Result<[f32; 3], String> {
    match v.get(key) {
        None | Some(Value::Null) => Ok(default),
        Some(Value::Array(a)) if a.len() == 3 => {
            let mut out = [0f32; 3];
            for (o, x) in out.iter_mut().zip(a) {
                *o = x
                    .as_f64()
                    .ok_or_else(|| format!("`{key}` entry {x} is not a number"))?
                    as f32;
            }
            Ok(out)
        }
        Some(Value::Number(n)) => {
            let x = n.as_f64().unwrap_or(f64::NAN) as f32;
            Ok([x; 3])
        }
        Some(o) => Err(format!("`{key}` {o} is not three numbers")),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    fn frame(seed: u32, w: u32, h: u32) -> Vec<u8> {
        (0..w * h * 3)
            .map(|i| {
                (i.wrapping_mul(2_654_435_761)
                    .wrapping_add(seed.wrapping_mul(97))
                    >> 7) as u8
            })
            .collect()
    }

    #[test]
    fn reads_clip_configs_old_and_new() {
        let new = json!({"crop_size": {"height": 224, "width": 224}, "do_center_crop": true,
            "do_normalize": true, "do_resize": true, "image_mean": CLIP_MEAN, "image_std": CLIP_STD,
            "resample": 3, "size": {"shortest_edge": 224}, "rescale_factor": 0.00392156862745098,
            "image_processor_type": "CLIPImageProcessor"});
        let p = ImageProcessor::from_preprocessor_config(&new).unwrap();
        assert_eq!(p, ImageProcessor::clip(224));
        // Old feature-extractor style: plain integers.
        let old = json!({"crop_size": 224, "size": 224, "feature_extractor_type": "CLIPFeatureExtractor"});
        assert_eq!(
            ImageProcessor::from_preprocessor_config(&old).unwrap(),
            ImageProcessor::clip(224)
        );
        // Nothing at all: transformers' defaults, which are CLIP's.
        assert_eq!(
            ImageProcessor::from_preprocessor_config(&json!({})).unwrap(),
            ImageProcessor::clip(224)
        );
        let exact = json!({"size": {"height": 256, "width": 320}, "do_center_crop": false,
            "resample": 2, "do_normalize": false});
        let p = ImageProcessor::from_preprocessor_config(&exact).unwrap();
        assert_eq!(
            p.resize,
            Some(ResizeTo::Exact {
                width: 320,
                height: 256
            })
        );
        assert_eq!(p.resample, Resample::Bilinear);
        assert_eq!(p.output_size(1280, 720), (320, 256));
        assert_eq!((p.mean, p.std), ([0.0; 3], [1.0; 3]));
    }

    #[test]
    fn bad_configs_are_config_errors_naming_the_field() {
        for (v, field) in [
            (json!({"resample": 1}), "resample"),
            (json!({"size": "big"}), "size"),
            (json!({"size": {"longest_edge": 3}}), "size"),
            (json!({"image_std": [1, 0, 1]}), "image_std"),
            (json!({"image_mean": [1, 2]}), "image_mean"),
            (json!({"crop_size": 300, "size": 224}), "crop"),
            (json!({"do_resize": "yes"}), "do_resize"),
            (json!({"rescale_factor": -1}), "rescale_factor"),
        ] {
            let e = ImageProcessor::from_preprocessor_config(&v).unwrap_err();
            assert_eq!(e.kind(), "bad_config");
            assert!(e.to_string().contains(field), "{v}: {e}");
        }
    }

    #[test]
    fn flat_colour_stays_flat_and_normalises_exactly() {
        let p = ImageProcessor::clip(16);
        let rgb: Vec<u8> = (0..40 * 24).flat_map(|_| [50u8, 128, 250]).collect();
        let mut out = vec![0f32; 3 * 16 * 16];
        p.process_into(
            FrameRef {
                width: 40,
                height: 24,
                rgb: &rgb,
            },
            &mut out,
        )
        .unwrap();
        for c in 0..3 {
            let want = ([50.0, 128.0, 250.0][c] / 255.0 - CLIP_MEAN[c]) / CLIP_STD[c];
            for v in &out[c * 256..(c + 1) * 256] {
                assert!((v - want).abs() < 1e-6, "{v} vs {want}");
            }
        }
    }

    #[test]
    fn crop_only_copies_the_center() {
        // No resize, crop 2x2 of a 4x2 frame: columns 1..3, untouched.
        let p = ImageProcessor {
            resize: None,
            crop: Some((2, 2)),
            ..ImageProcessor::clip(2)
        };
        let rgb = frame(3, 4, 2);
        let mut out = vec![0f32; 12];
        p.process_into(
            FrameRef {
                width: 4,
                height: 2,
                rgb: &rgb,
            },
            &mut out,
        )
        .unwrap();
        let t = p.table();
        for c in 0..3 {
            for y in 0..2 {
                for x in 0..2 {
                    let src = rgb[(y * 4 + x + 1) * 3 + c];
                    assert_eq!(out[c * 4 + y * 2 + x], t[c][src as usize]);
                }
            }
        }
    }

    #[test]
    fn batch_matches_single_frames_and_checks_sizes() {
        let p = ImageProcessor::clip(32);
        let frames: Vec<Vec<u8>> = (0..5).map(|s| frame(s, 96, 54)).collect();
        let refs: Vec<FrameRef> = frames
            .iter()
            .map(|rgb| FrameRef {
                width: 96,
                height: 54,
                rgb,
            })
            .collect();
        let (two, dims) = p
            .process_batch(&refs, NonZeroUsize::new(2).unwrap())
            .unwrap();
        let (one, _) = p
            .process_batch(&refs, NonZeroUsize::new(1).unwrap())
            .unwrap();
        assert_eq!(dims, (32, 32));
        assert_eq!(two, one);
        let mut single = vec![0f32; 3 * 32 * 32];
        p.process_into(refs[3], &mut single).unwrap();
        assert_eq!(&two[3 * 3072..4 * 3072], &single[..]);

        assert_eq!(
            p.process_batch(&[], NonZeroUsize::MIN).unwrap_err().kind(),
            "invalid_input"
        );
        let short = [0u8; 7];
        let bad = FrameRef {
            width: 2,
            height: 2,
            rgb: &short,
        };
        assert_eq!(
            p.process_batch(&[refs[0], bad], NonZeroUsize::MIN)
                .unwrap_err()
                .kind(),
            "invalid_input"
        );
        // Without a crop, frames of different shapes cannot share a batch.
        let free = ImageProcessor {
            crop: None,
            ..p.clone()
        };
        let other = frame(9, 40, 40);
        let e = free
            .process_batch(
                &[
                    refs[0],
                    FrameRef {
                        width: 40,
                        height: 40,
                        rgb: &other,
                    },
                ],
                NonZeroUsize::MIN,
            )
            .unwrap_err();
        assert!(e.to_string().contains("different sizes"), "{e}");
        // No resize and a frame smaller than the crop.
        let crop_only = ImageProcessor { resize: None, ..p };
        let tiny = frame(1, 8, 8);
        let e = crop_only
            .process_into(
                FrameRef {
                    width: 8,
                    height: 8,
                    rgb: &tiny,
                },
                &mut vec![0.0; 3072],
            )
            .unwrap_err();
        assert!(e.to_string().contains("smaller than"), "{e}");
    }
}
