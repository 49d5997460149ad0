//! A CLIP-style image processor as a checkpoint's processor config describes it (resize,
//! center-crop, rescale, normalise): `CLIPImageProcessor` for the CLIP embedders,
//! `VideoLlavaImageProcessor` / `VideoLlavaVideoProcessor` for VideoLLaVA.

use std::num::NonZeroUsize;

use serde_json::Value;

use super::{
    shortest_edge_dims, Arith, Normalize, Resample, ResizeTo, Resizer, OPENAI_CLIP_MEAN,
    OPENAI_CLIP_STD,
};
use crate::{FrameRef, ModelError};

/// The preprocessing of one model input: frame → normalised CHW floats.
#[derive(Debug, Clone, PartialEq)]
pub struct ImageProcessor {
    pub resize: Option<ResizeTo>,
    pub resample: Resample,
    /// Center crop `(width, height)` after the resize.
    pub crop: Option<(u32, u32)>,
    /// Multiplier from `u8` to the model's range (`do_rescale`'s `rescale_factor`), or none.
    pub rescale: Option<f64>,
    /// Per-channel mean and std; 0 and 1 when `do_normalize` is false.
    pub mean: [f64; 3],
    pub std: [f64; 3],
    pub normalize: bool,
    /// Whose resampling and float order: torch for transformers 5's fast (torchvision) image
    /// processors and every video processor, Pillow for the slow image processors.
    pub arith: Arith,
}

impl ImageProcessor {
    /// OpenAI CLIP's processor for a square input of `size` (transformers' defaults), with
    /// torch's arithmetic: transformers 5 loads `CLIPImageProcessor` configs into the fast
    /// (torchvision) processor.
    pub fn clip(size: u32) -> Self {
        Self {
            resize: Some(ResizeTo::ShortestEdge(size)),
            resample: Resample::Bicubic,
            crop: Some((size, size)),
            rescale: Some(1.0 / 255.0),
            mean: OPENAI_CLIP_MEAN,
            std: OPENAI_CLIP_STD,
            normalize: true,
            arith: Arith::Torch,
        }
    }

    /// Reads a processor config (CLIPImageProcessor / CLIPFeatureExtractor layout, VideoLLaVA's
    /// image and video processors). A field that is absent means what it means to transformers
    /// (its defaults are CLIP's). A crop larger than the resize is allowed (it pads).
    pub fn from_json(v: &Value, arith: Arith) -> Result<Self, ModelError> {
        let bad = |m: String| ModelError::BadConfig(format!("processor config: {m}"));
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
        let resample = match v.get("resample") {
            None | Some(Value::Null) => Resample::Bicubic,
            Some(r) => r.as_u64().and_then(Resample::from_pil).ok_or_else(|| {
                bad(format!(
                    "`resample` {r} is not supported (2 = bilinear, 3 = bicubic)"
                ))
            })?,
        };
        let rescale = if flag("do_rescale")? {
            Some(match v.get("rescale_factor") {
                None | Some(Value::Null) => 1.0 / 255.0,
                Some(f) => f
                    .as_f64()
                    .filter(|f| f.is_finite() && *f > 0.0)
                    .ok_or_else(|| bad(format!("`rescale_factor` {f} is not a positive number")))?,
            })
        } else {
            None
        };
        let normalize = flag("do_normalize")?;
        let (mean, std) = if normalize {
            (
                triple(v, "image_mean", OPENAI_CLIP_MEAN).map_err(bad)?,
                triple(v, "image_std", OPENAI_CLIP_STD).map_err(bad)?,
            )
        } else {
            ([0.0; 3], [1.0; 3])
        };
        if std.iter().any(|s| *s == 0.0 || !s.is_finite()) {
            return Err(bad(format!(
                "`image_std` {std:?} has a zero or non-finite entry"
            )));
        }
        Ok(Self {
            resize,
            resample,
            crop,
            rescale,
            mean,
            std,
            normalize,
            arith,
        })
    }

    /// A `preprocessor_config.json` for a fixed-size model input (the CLIP embedders): as
    /// [`from_json`](Self::from_json) with torch's arithmetic, and the crop must fit inside the
    /// resize. transformers would pad; no CLIP checkpoint is configured that way, so this
    /// refuses instead of inventing padding.
    pub fn from_preprocessor_config(v: &Value) -> Result<Self, ModelError> {
        let p = Self::from_json(v, Arith::Torch).map_err(|e| match e {
            ModelError::BadConfig(m) => {
                ModelError::BadConfig(m.replacen("processor config", "preprocessor_config.json", 1))
            }
            e => e,
        })?;
        if let Some((w, h)) = p.crop {
            let fits = match p.resize {
                Some(ResizeTo::ShortestEdge(s)) => w <= s && h <= s,
                Some(ResizeTo::Exact { width, height }) => w <= width && h <= height,
                None => true,
            };
            if !fits {
                return Err(ModelError::BadConfig(format!(
                    "preprocessor_config.json: crop {w}x{h} is larger than the resize {:?}",
                    p.resize
                )));
            }
        }
        Ok(p)
    }

    /// `(width, height)` after the resize, before the crop.
    pub fn resized(&self, w: u32, h: u32) -> (u32, u32) {
        match self.resize {
            Some(ResizeTo::ShortestEdge(s)) => {
                let (nw, nh) = shortest_edge_dims(w as usize, h as usize, s as usize);
                (nw as u32, nh as u32)
            }
            Some(ResizeTo::Exact { width, height }) => (width, height),
            None => (w, h),
        }
    }

    /// `(width, height)` of the model input this produces from a `w × h` frame.
    pub fn output_size(&self, w: u32, h: u32) -> (u32, u32) {
        self.crop.unwrap_or_else(|| self.resized(w, h))
    }

    /// [`output_size`](Self::output_size) in `usize`.
    pub fn output_dims(&self, w: usize, h: usize) -> (usize, usize) {
        let (w, h) = self.output_size(w as u32, h as u32);
        (w as usize, h as usize)
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

    /// The rescale and normalisation step.
    pub fn normalizer(&self) -> Normalize {
        Normalize {
            rescale: self.rescale,
            mean: self.mean,
            std: self.std,
            normalize: self.normalize,
            arith: self.arith,
        }
    }

    /// The uint8 image after resize and crop (HWC) and its `(w, h)`.
    pub fn resize_crop(&self, frame: FrameRef) -> Result<(Vec<u8>, usize, usize), ModelError> {
        let mut out = Vec::new();
        let (w, h) = self.resize_crop_with(&mut Resizer::new(), frame, &mut out)?;
        Ok((out, w, h))
    }

    fn resize_crop_with(
        &self,
        r: &mut Resizer,
        frame: FrameRef,
        out: &mut Vec<u8>,
    ) -> Result<(usize, usize), ModelError> {
        frame.validate()?;
        let (nw, nh) = self.resized(frame.width, frame.height);
        if nw == 0 || nh == 0 {
            return Err(ModelError::InvalidInput(format!(
                "frame {}x{} resizes to nothing",
                frame.width, frame.height
            )));
        }
        let crop = self.crop.map(|(w, h)| (w as usize, h as usize));
        r.resize_crop(
            frame,
            (nw as usize, nh as usize),
            crop,
            self.resample,
            self.arith,
            out,
        )
    }

    /// CHW f32 pixel values of a resized and cropped uint8 image.
    pub fn to_pixel_values(&self, img: &[u8], w: usize, h: usize) -> Vec<f32> {
        let mut out = vec![0f32; 3 * w * h];
        Normalize::hwc_to_chw(&self.normalizer().table(), &img[..3 * w * h], &mut out);
        out
    }

    /// Resize, crop, rescale, normalise: CHW f32 and `(w, h)`.
    pub fn apply(&self, frame: FrameRef) -> Result<(Vec<f32>, usize, usize), ModelError> {
        let (img, w, h) = self.resize_crop(frame)?;
        Ok((self.to_pixel_values(&img, w, h), w, h))
    }

    /// One frame into `out` (CHW, `3 × height × width` of [`output_size`](Self::output_size)).
    /// For fixed-size model inputs: a frame smaller than the crop (without a resize) is an
    /// error rather than padded.
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
    resizer: Resizer,
    table: [[f32; 256]; 3],
    rgb: Vec<u8>,
}

impl<'a> Worker<'a> {
    fn new(p: &'a ImageProcessor) -> Self {
        Self {
            p,
            resizer: Resizer::new(),
            table: p.normalizer().table(),
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
        self.p
            .resize_crop_with(&mut self.resizer, frame, &mut self.rgb)?;
        Normalize::hwc_to_chw(&self.table, &self.rgb, out);
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
            if let Some(n) = o.get("shortest_edge").filter(|n| !n.is_null()) {
                if o.get("longest_edge").is_some_and(|x| !x.is_null()) {
                    return Err("`longest_edge` is not supported".into());
                }
                return px(n).map(ResizeTo::ShortestEdge);
            }
            if o.get("longest_edge").is_some_and(|x| !x.is_null()) {
                return Err("`longest_edge` is not supported".into());
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

fn triple(v: &Value, key: &str, default: [f64; 3]) -> Result<[f64; 3], String> {
    match v.get(key) {
        None | Some(Value::Null) => Ok(default),
        Some(Value::Array(a)) if a.len() == 3 => {
            let mut out = [0f64; 3];
            for (o, x) in out.iter_mut().zip(a) {
                *o = x
                    .as_f64()
                    .ok_or_else(|| format!("`{key}` entry {x} is not a number"))?;
            }
            Ok(out)
        }
        Some(Value::Number(n)) => {
            let x = n.as_f64().unwrap_or(f64::NAN);
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
            "do_normalize": true, "do_resize": true, "image_mean": OPENAI_CLIP_MEAN,
            "image_std": OPENAI_CLIP_STD, "resample": 3, "size": {"shortest_edge": 224},
            "rescale_factor": 0.00392156862745098, "image_processor_type": "CLIPImageProcessor"});
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
        assert!(!p.normalize);
        // VideoLLaVA's processors: the same fields, whichever arithmetic.
        let v = json!({"size": {"shortest_edge": 40}, "crop_size": 32,
            "resample": 3, "image_mean": [0.5, 0.5, 0.5], "image_std": [0.5, 0.5, 0.5]});
        let o = ImageProcessor::from_json(&v, Arith::Pil).unwrap();
        assert_eq!(o.resize, Some(ResizeTo::ShortestEdge(40)));
        assert_eq!(o.crop, Some((32, 32)));
        assert_eq!(o.output_dims(64, 48), (32, 32));
        assert_eq!(o.arith, Arith::Pil);
        let no = ImageProcessor::from_json(
            &json!({"do_center_crop": false, "do_resize": false}),
            Arith::Pil,
        )
        .unwrap();
        assert_eq!(no.output_dims(7, 5), (7, 5));
        // A crop larger than the resize pads (transformers) unless the input is fixed-size.
        let pad = json!({"crop_size": 300, "size": 224});
        assert!(ImageProcessor::from_json(&pad, Arith::Pil).is_ok());
    }

    #[test]
    fn bad_configs_are_config_errors_naming_the_field() {
        for (v, field) in [
            (json!({"resample": 1}), "resample"),
            (json!({"size": "big"}), "size"),
            (json!({"size": {"longest_edge": 3}}), "size"),
            (
                json!({"size": {"shortest_edge": 4, "longest_edge": 9}}),
                "longest_edge",
            ),
            (json!({"image_std": [1, 0, 1]}), "image_std"),
            (json!({"image_mean": [1, 2]}), "image_mean"),
            (json!({"crop_size": 300, "size": 224}), "crop"),
            (json!({"do_resize": "yes"}), "do_resize"),
            (json!({"rescale_factor": -1}), "rescale_factor"),
        ] {
            let e = ImageProcessor::from_preprocessor_config(&v).unwrap_err();
            assert_eq!(e.kind(), "bad_config");
            assert!(e.to_string().contains(field), "{v}: {e}");
            assert!(
                e.to_string().contains("preprocessor_config.json"),
                "{v}: {e}"
            );
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
            let want = (([50.0, 128.0, 250.0][c] / 255.0 - OPENAI_CLIP_MEAN[c])
                / OPENAI_CLIP_STD[c]) as f32;
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
        let t = p.normalizer().table();
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
    fn apply_equals_process_into() {
        let rgb = frame(5, 96, 54);
        let f = FrameRef {
            width: 96,
            height: 54,
            rgb: &rgb,
        };
        for arith in [Arith::Torch, Arith::Pil] {
            let p = ImageProcessor {
                arith,
                ..ImageProcessor::clip(32)
            };
            let (a, w, h) = p.apply(f).unwrap();
            assert_eq!((w, h), (32, 32));
            let mut b = vec![0f32; a.len()];
            p.process_into(f, &mut b).unwrap();
            assert_eq!(a, b);
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
