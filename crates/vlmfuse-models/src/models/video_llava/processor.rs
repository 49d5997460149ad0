//! `VideoLlavaProcessor` as transformers 5.23 runs it: the video processor (torchvision on
//! uint8 tensors), the image processor (PIL), the tokenizer as transformers rebuilds it, the
//! placeholder expansion and the chat format.
//!
//! Both image paths resize in 8-bit fixed point and round to uint8 between the horizontal and
//! the vertical pass, exactly as their reference does; they differ only in the precision of the
//! fixed-point weights (torch picks the largest that fits int16 per axis, PIL always uses 22
//! bits) and in the float order of the bicubic kernel, so each is reproduced bit for bit.

use std::str::FromStr;

use tokenizers::Tokenizer;

use super::config::{SelectStrategy, VideoLlavaConfig};
use crate::weights::WeightSource;
use crate::{FrameRef, ModelError};

/// OpenAI CLIP statistics, transformers' `OPENAI_CLIP_MEAN` / `OPENAI_CLIP_STD`.
#[allow(clippy::excessive_precision)]
pub const OPENAI_CLIP_MEAN: [f64; 3] = [0.48145466, 0.4578275, 0.40821073];
#[allow(clippy::excessive_precision)]
pub const OPENAI_CLIP_STD: [f64; 3] = [0.26862954, 0.26130258, 0.27577711];

/// The resampling filter (PIL's numbering in configs: 2 = bilinear, 3 = bicubic).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Resample {
    Bilinear,
    Bicubic,
}

/// Whose fixed-point arithmetic and float rounding to reproduce.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Arith {
    /// torch's native uint8 antialiased interpolation (what torchvision's `resize` runs on a
    /// uint8 tensor); normalisation `(x - 255·mean) / (255·std)` in f32.
    Torch,
    /// Pillow's `Image.resize`; rescale in f64 then `(x - mean) / std` in f32.
    Pil,
}

struct AxisCoeffs {
    xmin: Vec<usize>,
    xsize: Vec<usize>,
    /// `ksize` fixed-point weights per output sample.
    k: Vec<i64>,
    ksize: usize,
    precision: u32,
}

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

fn clip8(acc: i64, precision: u32) -> u8 {
    (acc >> precision).clamp(0, 255) as u8
}

/// Antialiased resize of packed RGB8 to `out_w × out_h`, horizontal pass first, rounded to u8
/// after each pass (both references do; a pass whose size does not change is skipped).
pub fn resize_rgb8(
    frame: FrameRef,
    out_w: usize,
    out_h: usize,
    kind: Resample,
    arith: Arith,
) -> Result<Vec<u8>, ModelError> {
    frame.validate()?;
    if out_w == 0 || out_h == 0 {
        return Err(ModelError::InvalidInput(format!(
            "resize target {out_w}x{out_h}"
        )));
    }
    let (in_w, in_h) = (frame.width as usize, frame.height as usize);
    let mut cur = frame.rgb.to_vec();
    let mut cur_w = in_w;
    if out_w != in_w {
        let c = axis_coeffs(in_w, out_w, kind, arith);
        let half = 1i64 << (c.precision - 1);
        let mut next = vec![0u8; in_h * out_w * 3];
        for y in 0..in_h {
            let row = &cur[y * in_w * 3..(y + 1) * in_w * 3];
            for xo in 0..out_w {
                let k = &c.k[xo * c.ksize..xo * c.ksize + c.xsize[xo]];
                let mut acc = [half; 3];
                for (j, &kj) in k.iter().enumerate() {
                    let p = &row[(c.xmin[xo] + j) * 3..(c.xmin[xo] + j) * 3 + 3];
                    for ch in 0..3 {
                        acc[ch] += p[ch] as i64 * kj;
                    }
                }
                for ch in 0..3 {
                    next[(y * out_w + xo) * 3 + ch] = clip8(acc[ch], c.precision);
                }
            }
        }
        cur = next;
        cur_w = out_w;
    }
    if out_h != in_h {
        let c = axis_coeffs(in_h, out_h, kind, arith);
        let half = 1i64 << (c.precision - 1);
        let mut next = vec![0u8; out_h * cur_w * 3];
        for yo in 0..out_h {
            let k = &c.k[yo * c.ksize..yo * c.ksize + c.xsize[yo]];
            for x in 0..cur_w {
                let mut acc = [half; 3];
                for (j, &kj) in k.iter().enumerate() {
                    let p = &cur[((c.xmin[yo] + j) * cur_w + x) * 3..][..3];
                    for ch in 0..3 {
                        acc[ch] += p[ch] as i64 * kj;
                    }
                }
                for ch in 0..3 {
                    next[(yo * cur_w + x) * 3 + ch] = clip8(acc[ch], c.precision);
                }
            }
        }
        cur = next;
    }
    Ok(cur)
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

/// Center crop to `ch × cw`, zero-padding first where the image is smaller (transformers'
/// `center_crop`: pad `(c - s) // 2` before, the rest after; top/left `int((s - c) / 2)`).
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

/// How a processor resizes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ResizeTo {
    ShortestEdge(usize),
    Exact { width: usize, height: usize },
}

/// One image or video processor config: resize, crop, rescale, normalise.
#[derive(Debug, Clone, PartialEq)]
pub struct ImageOps {
    pub resize: Option<ResizeTo>,
    pub resample: Resample,
    /// `(width, height)`.
    pub crop: Option<(usize, usize)>,
    pub rescale: Option<f64>,
    pub mean: [f64; 3],
    pub std: [f64; 3],
    pub normalize: bool,
    pub arith: Arith,
}

fn size_field(v: &serde_json::Value, square: bool) -> Result<Option<ResizeTo>, ModelError> {
    Ok(match v {
        serde_json::Value::Null => None,
        serde_json::Value::Number(n) => {
            let n = n.as_u64().unwrap_or(0) as usize;
            Some(if square {
                ResizeTo::Exact {
                    width: n,
                    height: n,
                }
            } else {
                ResizeTo::ShortestEdge(n)
            })
        }
        serde_json::Value::Object(o) => {
            let g = |k: &str| o.get(k).and_then(|x| x.as_u64()).map(|x| x as usize);
            if o.get("longest_edge").is_some_and(|x| !x.is_null()) {
                return Err(ModelError::BadConfig(
                    "processor size with `longest_edge` is not supported for CLIP preprocessing"
                        .into(),
                ));
            }
            match (g("shortest_edge"), g("height"), g("width")) {
                (Some(s), _, _) => Some(ResizeTo::ShortestEdge(s)),
                (None, Some(h), Some(w)) => Some(ResizeTo::Exact {
                    width: w,
                    height: h,
                }),
                _ => {
                    return Err(ModelError::BadConfig(format!(
                        "processor size {v} has neither shortest_edge nor height+width"
                    )))
                }
            }
        }
        other => {
            return Err(ModelError::BadConfig(format!(
                "processor size {other} is not a number or an object"
            )))
        }
    })
}

fn triple(v: Option<&serde_json::Value>, default: [f64; 3]) -> Result<[f64; 3], ModelError> {
    match v {
        None | Some(serde_json::Value::Null) => Ok(default),
        Some(serde_json::Value::Number(n)) => {
            let x = n.as_f64().unwrap_or(0.0);
            Ok([x, x, x])
        }
        Some(serde_json::Value::Array(a)) if a.len() == 3 => {
            let mut out = [0.0; 3];
            for (o, x) in out.iter_mut().zip(a) {
                *o = x.as_f64().ok_or_else(|| {
                    ModelError::BadConfig(format!("image_mean/std entry {x} is not a number"))
                })?;
            }
            Ok(out)
        }
        Some(other) => Err(ModelError::BadConfig(format!(
            "image_mean/std {other} is not three numbers"
        ))),
    }
}

impl ImageOps {
    /// CLIP defaults (what `VideoLlavaImageProcessor` and `VideoLlavaVideoProcessor` use when a
    /// field is missing).
    pub fn clip_default(arith: Arith) -> Self {
        Self {
            resize: Some(ResizeTo::ShortestEdge(224)),
            resample: Resample::Bicubic,
            crop: Some((224, 224)),
            rescale: Some(1.0 / 255.0),
            mean: OPENAI_CLIP_MEAN,
            std: OPENAI_CLIP_STD,
            normalize: true,
            arith,
        }
    }

    /// Reads a (video) preprocessor config; absent fields keep [`ImageOps::clip_default`].
    pub fn from_json(v: &serde_json::Value, arith: Arith) -> Result<Self, ModelError> {
        let mut o = Self::clip_default(arith);
        let flag = |k: &str, d: bool| v.get(k).and_then(|x| x.as_bool()).unwrap_or(d);
        if v.get("size").is_some() {
            o.resize = size_field(&v["size"], false)?;
        }
        if !flag("do_resize", true) {
            o.resize = None;
        }
        if v.get("crop_size").is_some() {
            o.crop = size_field(&v["crop_size"], true)?.map(|r| match r {
                ResizeTo::Exact { width, height } => (width, height),
                ResizeTo::ShortestEdge(s) => (s, s),
            });
        }
        if !flag("do_center_crop", true) {
            o.crop = None;
        }
        if let Some(r) = v.get("resample").filter(|x| !x.is_null()) {
            o.resample = match r.as_u64() {
                Some(2) => Resample::Bilinear,
                Some(3) => Resample::Bicubic,
                _ => {
                    return Err(ModelError::BadConfig(format!(
                        "resample {r} is not supported (2 = bilinear, 3 = bicubic)"
                    )))
                }
            };
        }
        let factor = v
            .get("rescale_factor")
            .and_then(|x| x.as_f64())
            .unwrap_or(1.0 / 255.0);
        o.rescale = flag("do_rescale", true).then_some(factor);
        o.mean = triple(v.get("image_mean"), OPENAI_CLIP_MEAN)?;
        o.std = triple(v.get("image_std"), OPENAI_CLIP_STD)?;
        o.normalize = flag("do_normalize", true);
        if o.std.contains(&0.0) {
            return Err(ModelError::BadConfig("image_std has a zero".into()));
        }
        Ok(o)
    }

    /// Size after resize and crop, `(w, h)`.
    pub fn output_dims(&self, w: usize, h: usize) -> (usize, usize) {
        let (w, h) = match self.resize {
            None => (w, h),
            Some(ResizeTo::ShortestEdge(s)) => shortest_edge_dims(w, h, s),
            Some(ResizeTo::Exact { width, height }) => (width, height),
        };
        self.crop.unwrap_or((w, h))
    }

    /// The uint8 image after resize and crop (HWC) and its `(w, h)`.
    pub fn resize_crop(&self, frame: FrameRef) -> Result<(Vec<u8>, usize, usize), ModelError> {
        frame.validate()?;
        let (w0, h0) = (frame.width as usize, frame.height as usize);
        let (mut img, mut w, mut h) = match self.resize {
            None => (frame.rgb.to_vec(), w0, h0),
            Some(r) => {
                let (w, h) = match r {
                    ResizeTo::ShortestEdge(s) => shortest_edge_dims(w0, h0, s),
                    ResizeTo::Exact { width, height } => (width, height),
                };
                if w == 0 || h == 0 {
                    return Err(ModelError::InvalidInput(format!(
                        "frame {w0}x{h0} resizes to nothing"
                    )));
                }
                (resize_rgb8(frame, w, h, self.resample, self.arith)?, w, h)
            }
        };
        if let Some((cw, ch)) = self.crop {
            img = center_crop_rgb8(&img, w, h, cw, ch);
            (w, h) = (cw, ch);
        }
        Ok((img, w, h))
    }

    /// CHW f32 pixel values, as the reference's rescale and normalise compute them.
    pub fn to_pixel_values(&self, img: &[u8], w: usize, h: usize) -> Vec<f32> {
        let n = w * h;
        let mut out = vec![0f32; 3 * n];
        // Per-channel affine maps in the reference's float order.
        let f: [Box<dyn Fn(u8) -> f32>; 3] = std::array::from_fn(|c| -> Box<dyn Fn(u8) -> f32> {
            let (m, s) = (self.mean[c], self.std[c]);
            match (self.arith, self.rescale, self.normalize) {
                (Arith::Torch, Some(r), true) => {
                    // Fused: mean and std (f32 tensors) times 1/rescale in f32.
                    let k = (1.0 / r) as f32;
                    let (m, s) = (m as f32 * k, s as f32 * k);
                    Box::new(move |x| (x as f32 - m) / s)
                }
                (Arith::Torch, None, true) => {
                    let (m, s) = (m as f32, s as f32);
                    Box::new(move |x| (x as f32 - m) / s)
                }
                (Arith::Pil, Some(r), true) => {
                    let (m, s) = (m as f32, s as f32);
                    Box::new(move |x| ((x as f64 * r) as f32 - m) / s)
                }
                (Arith::Pil, None, true) => {
                    let (m, s) = (m as f32, s as f32);
                    Box::new(move |x| (x as f32 - m) / s)
                }
                (Arith::Torch, Some(r), false) => {
                    let r = r as f32;
                    Box::new(move |x| x as f32 * r)
                }
                (Arith::Pil, Some(r), false) => Box::new(move |x| (x as f64 * r) as f32),
                (_, None, false) => Box::new(|x| x as f32),
            }
        });
        for i in 0..n {
            for c in 0..3 {
                out[c * n + i] = f[c](img[i * 3 + c]);
            }
        }
        out
    }

    /// Resize, crop, rescale, normalise: CHW f32 and `(w, h)`.
    pub fn apply(&self, frame: FrameRef) -> Result<(Vec<f32>, usize, usize), ModelError> {
        let (img, w, h) = self.resize_crop(frame)?;
        Ok((self.to_pixel_values(&img, w, h), w, h))
    }
}

/// What the tokenizer needs to know from `tokenizer_config.json`.
#[derive(Debug, Clone, Default)]
struct TokenizerSettings {
    class: Option<String>,
    legacy: Option<bool>,
    add_prefix_space: Option<bool>,
    add_bos_token: Option<bool>,
    add_eos_token: Option<bool>,
    bos: Option<String>,
    eos: Option<String>,
    pad: Option<String>,
}

fn token_str(v: Option<&serde_json::Value>) -> Option<String> {
    match v? {
        serde_json::Value::String(s) => Some(s.clone()),
        serde_json::Value::Object(o) => o.get("content")?.as_str().map(str::to_string),
        _ => None,
    }
}

impl TokenizerSettings {
    fn from_json(v: &serde_json::Value) -> Self {
        let b = |k: &str| v.get(k).and_then(|x| x.as_bool());
        Self {
            class: v
                .get("tokenizer_class")
                .and_then(|x| x.as_str())
                .map(str::to_string),
            legacy: b("legacy"),
            add_prefix_space: b("add_prefix_space"),
            add_bos_token: b("add_bos_token"),
            add_eos_token: b("add_eos_token"),
            bos: token_str(v.get("bos_token")),
            eos: token_str(v.get("eos_token")),
            pad: token_str(v.get("pad_token")),
        }
    }
}

/// Loads `tokenizer.json` the way transformers 5.23 does for this checkpoint. For
/// `LlamaTokenizer` (what Video-LLaVA names) transformers keeps only the vocabulary, merges and
/// post-processor of the file and rebuilds the rest: no normalizer, a `Metaspace` pre-tokenizer
/// (prepend `first` unless `legacy`, `never` without `add_prefix_space`), byte fallback, and a
/// BOS/EOS template when `add_bos_token`/`add_eos_token` are set. A file written by an older
/// transformers (a `Prepend`+`Replace` normalizer) therefore tokenizes differently there than
/// when read verbatim, and it is the rebuilt behaviour that the model sees in the reference.
fn load_tokenizer(source: &WeightSource) -> Result<(Tokenizer, TokenizerSettings), ModelError> {
    let path = source.resolve("tokenizer.json")?;
    let text = std::fs::read_to_string(&path).map_err(|e| ModelError::Io {
        path: path.clone(),
        source: e,
    })?;
    let settings = match source.resolve_optional("tokenizer_config.json")? {
        Some(_) => TokenizerSettings::from_json(&source.read_json("tokenizer_config.json")?),
        None => TokenizerSettings::default(),
    };
    let bad = |e: String| ModelError::BadWeights {
        path: path.clone(),
        reason: e,
    };
    let mut j: serde_json::Value = serde_json::from_str(&text).map_err(|e| bad(e.to_string()))?;
    let is_llama = matches!(
        settings.class.as_deref(),
        Some("LlamaTokenizer") | Some("LlamaTokenizerFast")
    );
    if is_llama {
        let model = j
            .get_mut("model")
            .and_then(|m| m.as_object_mut())
            .ok_or_else(|| bad("no `model` object".into()))?;
        if model.get("type").and_then(|t| t.as_str()) != Some("BPE") {
            return Err(bad(
                "LlamaTokenizer needs a BPE tokenizer.json (found another model type)".into(),
            ));
        }
        model.insert("fuse_unk".into(), true.into());
        model.insert("byte_fallback".into(), true.into());
        model.insert("dropout".into(), serde_json::Value::Null);
        model.insert("continuing_subword_prefix".into(), serde_json::Value::Null);
        model.insert("end_of_word_suffix".into(), serde_json::Value::Null);
        model.insert("ignore_merges".into(), false.into());
        let add_prefix_space = settings.add_prefix_space.unwrap_or(true);
        let scheme = if !add_prefix_space {
            "never"
        } else if settings.legacy.unwrap_or(false) {
            "always"
        } else {
            "first"
        };
        j["normalizer"] = serde_json::Value::Null;
        j["pre_tokenizer"] = serde_json::json!({
            "type": "Metaspace", "replacement": "▁", "prepend_scheme": scheme, "split": false
        });
        let mut decoders = vec![
            serde_json::json!({"type": "Replace", "pattern": {"String": "▁"}, "content": " "}),
            serde_json::json!({"type": "ByteFallback"}),
            serde_json::json!({"type": "Fuse"}),
        ];
        if add_prefix_space {
            decoders
                .push(serde_json::json!({"type": "Strip", "content": " ", "start": 1, "stop": 0}));
        }
        j["decoder"] = serde_json::json!({"type": "Sequence", "decoders": decoders});
    }
    let explicit = settings.add_bos_token.is_some() || settings.add_eos_token.is_some();
    if explicit || j.get("post_processor").is_none_or(|p| p.is_null()) {
        // transformers' `update_post_processor`: `[bos] $A [eos]` as the flags say (Llama's
        // default is BOS on, EOS off).
        let vocab_id = |tok: &str| -> Option<u64> {
            j.get("added_tokens")
                .and_then(|a| a.as_array())
                .and_then(|a| {
                    a.iter()
                        .find(|t| t.get("content").and_then(|c| c.as_str()) == Some(tok))
                        .and_then(|t| t.get("id")?.as_u64())
                })
                .or_else(|| j["model"]["vocab"].get(tok).and_then(|x| x.as_u64()))
        };
        let default_bos = is_llama;
        let add_bos = settings.add_bos_token.unwrap_or(default_bos);
        let add_eos = settings.add_eos_token.unwrap_or(false);
        let bos = settings.bos.clone().unwrap_or_else(|| "<s>".into());
        let eos = settings.eos.clone().unwrap_or_else(|| "</s>".into());
        let mut single = Vec::new();
        let mut specials = serde_json::Map::new();
        let mut push = |tok: &str, list: &mut Vec<serde_json::Value>| -> Result<(), ModelError> {
            let id = vocab_id(tok)
                .ok_or_else(|| bad(format!("special token `{tok}` is not in the vocabulary")))?;
            list.push(serde_json::json!({"SpecialToken": {"id": tok, "type_id": 0}}));
            specials.insert(
                tok.into(),
                serde_json::json!({"id": tok, "ids": [id], "tokens": [tok]}),
            );
            Ok(())
        };
        if add_bos {
            push(&bos, &mut single)?;
        }
        single.push(serde_json::json!({"Sequence": {"id": "A", "type_id": 0}}));
        if add_eos {
            push(&eos, &mut single)?;
        }
        let mut pair = single.clone();
        pair.push(serde_json::json!({"Sequence": {"id": "B", "type_id": 1}}));
        j["post_processor"] = serde_json::json!({
            "type": "TemplateProcessing", "single": single, "pair": pair,
            "special_tokens": specials
        });
    }
    let tok = Tokenizer::from_str(&j.to_string()).map_err(|e| bad(e.to_string()))?;
    Ok((tok, settings))
}

/// The preprocessed frames of one clip: `frames × 3 × height × width`, CHW per frame.
#[derive(Debug, Clone, PartialEq)]
pub struct VideoPixels {
    pub data: Vec<f32>,
    pub frames: usize,
    pub height: usize,
    pub width: usize,
}

/// One preprocessed image: `3 × height × width`.
#[derive(Debug, Clone, PartialEq)]
pub struct ImagePixels {
    pub data: Vec<f32>,
    pub height: usize,
    pub width: usize,
}

/// Token ids of a batch, left-padded to one length, with the mask of real tokens.
#[derive(Debug, Clone, PartialEq)]
pub struct EncodedBatch {
    pub input_ids: Vec<Vec<u32>>,
    pub attention_mask: Vec<Vec<bool>>,
}

impl EncodedBatch {
    pub fn batch(&self) -> usize {
        self.input_ids.len()
    }

    pub fn seq_len(&self) -> usize {
        self.input_ids.first().map(|r| r.len()).unwrap_or(0)
    }
}

/// `VideoLlavaProcessor`: everything between decoded frames + user text and model inputs.
pub struct VideoLlavaProcessor {
    pub video: ImageOps,
    pub image: ImageOps,
    /// Patch size the placeholder expansion assumes (processor config; the tower's by default).
    pub patch_size: usize,
    /// Tokens beyond the patch grid per frame (CLS).
    pub num_additional_image_tokens: usize,
    pub select_strategy: SelectStrategy,
    /// Frames per clip the model takes (Video-LLaVA was trained on 8).
    pub num_frames: usize,
    tokenizer: Tokenizer,
    pub image_token: String,
    pub video_token: String,
    pub image_token_id: u32,
    pub video_token_id: u32,
    pub pad_token_id: u32,
    pub eos_token_ids: Vec<u32>,
}

/// Frames per clip when the config does not say: the number Video-LLaVA was trained with.
pub const DEFAULT_NUM_FRAMES: usize = 8;

impl VideoLlavaProcessor {
    /// Reads the processor configs the way transformers resolves them: the video processor from
    /// `processor_config.json`'s `video_processor`, else `video_preprocessor_config.json`, else
    /// `preprocessor_config.json`; the image processor from `processor_config.json`'s
    /// `image_processor`, else `preprocessor_config.json`.
    pub fn load(source: &WeightSource, cfg: &VideoLlavaConfig) -> Result<Self, ModelError> {
        let opt = |f: &str| -> Result<Option<serde_json::Value>, ModelError> {
            match source.resolve_optional(f)? {
                Some(_) => Ok(Some(source.read_json(f)?)),
                None => Ok(None),
            }
        };
        let proc = opt("processor_config.json")?;
        let pre = opt("preprocessor_config.json")?;
        let vpre = opt("video_preprocessor_config.json")?;
        let nested = |k: &str| proc.as_ref().and_then(|p| p.get(k)).cloned();
        let video_cfg = nested("video_processor").or(vpre).or(pre.clone());
        let image_cfg = nested("image_processor").or(pre);
        let video = match &video_cfg {
            Some(v) => ImageOps::from_json(v, Arith::Torch)?,
            None => ImageOps::clip_default(Arith::Torch),
        };
        let image = match &image_cfg {
            Some(v) => ImageOps::from_json(v, Arith::Pil)?,
            None => ImageOps::clip_default(Arith::Pil),
        };
        let pget = |k: &str| {
            proc.as_ref()
                .and_then(|p| p.get(k))
                .filter(|x| !x.is_null())
        };
        let patch_size = pget("patch_size")
            .and_then(|x| x.as_u64())
            .map(|x| x as usize)
            .unwrap_or(cfg.vision.patch_size);
        let num_additional_image_tokens = pget("num_additional_image_tokens")
            .and_then(|x| x.as_u64())
            .map(|x| x as usize)
            .unwrap_or(1);
        let select_strategy = match pget("vision_feature_select_strategy").and_then(|x| x.as_str())
        {
            None => cfg.select_strategy,
            Some("default") => SelectStrategy::Default,
            Some("full") => SelectStrategy::Full,
            Some(o) => {
                return Err(ModelError::BadConfig(format!(
                    "processor vision_feature_select_strategy `{o}`"
                )))
            }
        };
        let num_frames = video_cfg
            .as_ref()
            .and_then(|v| v.get("num_frames"))
            .and_then(|x| x.as_u64())
            .map(|x| x as usize)
            .unwrap_or(DEFAULT_NUM_FRAMES)
            .max(1);
        let (tokenizer, ts) = load_tokenizer(source)?;
        let image_token = pget("image_token")
            .and_then(|x| x.as_str())
            .unwrap_or("<image>")
            .to_string();
        let video_token = pget("video_token")
            .and_then(|x| x.as_str())
            .unwrap_or("<video>")
            .to_string();
        let id_of = |t: &str| {
            tokenizer
                .token_to_id(t)
                .ok_or_else(|| ModelError::BadConfig(format!("tokenizer has no `{t}` token")))
        };
        let image_token_id = id_of(&image_token)?;
        let video_token_id = id_of(&video_token)?;
        for (name, got, want) in [
            ("image", image_token_id, cfg.image_token_id),
            ("video", video_token_id, cfg.video_token_id),
        ] {
            if got != want {
                return Err(ModelError::BadConfig(format!(
                    "tokenizer maps the {name} token to {got}, config.json says {want}"
                )));
            }
        }
        let pad_token_id = ts
            .pad
            .as_deref()
            .and_then(|p| tokenizer.token_to_id(p))
            .or(cfg.pad_token_id)
            .unwrap_or(0);
        let mut eos_token_ids = Vec::new();
        if let Some(g) = opt("generation_config.json")? {
            eos_token_ids.extend(ids_of(g.get("eos_token_id")));
        }
        if eos_token_ids.is_empty() {
            if let Some(id) = ts.eos.as_deref().and_then(|e| tokenizer.token_to_id(e)) {
                eos_token_ids.push(id);
            }
        }
        Ok(Self {
            video,
            image,
            patch_size,
            num_additional_image_tokens,
            select_strategy,
            num_frames,
            tokenizer,
            image_token,
            video_token,
            image_token_id,
            video_token_id,
            pad_token_id,
            eos_token_ids,
        })
    }

    pub fn tokenizer(&self) -> &Tokenizer {
        &self.tokenizer
    }

    /// The Video-LLaVA chat format for one user turn about one clip.
    pub fn video_prompt(&self, user: &str) -> String {
        format!("USER: {}\n{user} ASSISTANT:", self.video_token)
    }

    /// The same for one image.
    pub fn image_prompt(&self, user: &str) -> String {
        format!("USER: {}\n{user} ASSISTANT:", self.image_token)
    }

    /// `n` indices spread over `total` frames as the Video-LLaVA examples pick them
    /// (`np.arange(0, total, total / n).astype(int)`); every frame when there are `n` or fewer.
    pub fn sample_indices(total: usize, n: usize) -> Vec<usize> {
        if total <= n || n == 0 {
            return (0..total).collect();
        }
        let step = total as f64 / n as f64;
        (0..n)
            .map(|i| ((i as f64 * step) as usize).min(total - 1))
            .collect()
    }

    /// Picks [`num_frames`](Self::num_frames) of `frames` and preprocesses them. All frames of
    /// a clip must have one size (they come from one stream).
    pub fn preprocess_video(&self, frames: &[FrameRef]) -> Result<VideoPixels, ModelError> {
        if frames.is_empty() {
            return Err(ModelError::InvalidInput("a clip with no frames".into()));
        }
        let idx = Self::sample_indices(frames.len(), self.num_frames);
        let mut data = Vec::new();
        let mut dims = None;
        for &i in &idx {
            let (px, w, h) = self.video.apply(frames[i])?;
            match dims {
                None => dims = Some((w, h)),
                Some(d) if d != (w, h) => {
                    return Err(ModelError::InvalidInput(format!(
                        "frames of one clip preprocess to different sizes ({}x{} and {w}x{h})",
                        d.0, d.1
                    )))
                }
                _ => {}
            }
            data.extend(px);
        }
        let (width, height) = dims.expect("at least one frame");
        Ok(VideoPixels {
            data,
            frames: idx.len(),
            height,
            width,
        })
    }

    pub fn preprocess_image(&self, image: FrameRef) -> Result<ImagePixels, ModelError> {
        let (data, width, height) = self.image.apply(image)?;
        Ok(ImagePixels {
            data,
            height,
            width,
        })
    }

    /// Placeholders one clip expands to: `(h / p)·(w / p) + extra` per frame, every frame (the
    /// video path keeps CLS whatever the select strategy).
    pub fn video_token_count(&self, v: &VideoPixels) -> usize {
        let per = (v.height / self.patch_size) * (v.width / self.patch_size)
            + self.num_additional_image_tokens;
        per * v.frames
    }

    /// Placeholders one image expands to (minus CLS under the `default` strategy).
    pub fn image_token_count(&self, i: &ImagePixels) -> usize {
        let n = (i.height / self.patch_size) * (i.width / self.patch_size)
            + self.num_additional_image_tokens;
        match self.select_strategy {
            SelectStrategy::Default => n.saturating_sub(1),
            SelectStrategy::Full => n,
        }
    }

    /// Replaces each `<video>` / `<image>` in `text` (in order) by its run of placeholders, as
    /// `ProcessorMixin.get_text_with_replacements` does. Counts must match.
    pub fn expand(
        &self,
        text: &str,
        videos: &[usize],
        images: &[usize],
    ) -> Result<String, ModelError> {
        let mut out = String::with_capacity(text.len());
        let (mut vi, mut ii) = (0, 0);
        let mut rest = text;
        loop {
            let nv = rest.find(&self.video_token);
            let ni = rest.find(&self.image_token);
            let (at, is_video) = match (nv, ni) {
                (None, None) => break,
                (Some(a), None) => (a, true),
                (None, Some(b)) => (b, false),
                (Some(a), Some(b)) => {
                    if a <= b {
                        (a, true)
                    } else {
                        (b, false)
                    }
                }
            };
            out.push_str(&rest[..at]);
            let (tok, counts, k) = if is_video {
                (&self.video_token, videos, &mut vi)
            } else {
                (&self.image_token, images, &mut ii)
            };
            let n = *counts.get(*k).ok_or_else(|| {
                ModelError::InvalidInput(format!(
                    "the prompt has more {tok} placeholders than inputs ({})",
                    counts.len()
                ))
            })?;
            *k += 1;
            out.push_str(&tok.repeat(n));
            rest = &rest[at + tok.len()..];
        }
        out.push_str(rest);
        if vi != videos.len() || ii != images.len() {
            return Err(ModelError::InvalidInput(format!(
                "the prompt has {vi} {} and {ii} {} placeholders for {} clip(s) and {} image(s)",
                self.video_token,
                self.image_token,
                videos.len(),
                images.len()
            )));
        }
        Ok(out)
    }

    /// Token ids with the tokenizer's special tokens (BOS for Llama).
    pub fn encode(&self, text: &str) -> Result<Vec<u32>, ModelError> {
        let enc = self
            .tokenizer
            .encode(text, true)
            .map_err(|e| ModelError::InvalidInput(format!("tokenizer: {e}")))?;
        Ok(enc.get_ids().to_vec())
    }

    /// Left-pads encoded rows to one length (generation needs every row's last token at the
    /// same index).
    pub fn pad_left(&self, rows: Vec<Vec<u32>>) -> EncodedBatch {
        let len = rows.iter().map(|r| r.len()).max().unwrap_or(0);
        let mut input_ids = Vec::with_capacity(rows.len());
        let mut attention_mask = Vec::with_capacity(rows.len());
        for r in rows {
            let pad = len - r.len();
            let mut ids = vec![self.pad_token_id; pad];
            ids.extend_from_slice(&r);
            let mut m = vec![false; pad];
            m.extend(std::iter::repeat_n(true, r.len()));
            input_ids.push(ids);
            attention_mask.push(m);
        }
        EncodedBatch {
            input_ids,
            attention_mask,
        }
    }

    pub fn decode(&self, ids: &[u32], skip_special: bool) -> Result<String, ModelError> {
        self.tokenizer
            .decode(ids, skip_special)
            .map_err(|e| ModelError::InvalidInput(format!("tokenizer: {e}")))
    }
}

/// `eos_token_id` may be a number or a list.
fn ids_of(v: Option<&serde_json::Value>) -> Vec<u32> {
    match v {
        Some(serde_json::Value::Number(n)) => {
            n.as_u64().map(|x| vec![x as u32]).unwrap_or_default()
        }
        Some(serde_json::Value::Array(a)) => a
            .iter()
            .filter_map(|x| x.as_u64().map(|x| x as u32))
            .collect(),
        _ => Vec::new(),
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
    fn flat_colour_survives_both_resamplers_exactly() {
        let rgb = frame(37, 23, |_, _, c| [7u8, 128, 250][c]);
        let f = FrameRef {
            width: 37,
            height: 23,
            rgb: &rgb,
        };
        for arith in [Arith::Torch, Arith::Pil] {
            for kind in [Resample::Bicubic, Resample::Bilinear] {
                for (w, h) in [(16, 9), (80, 50), (37, 11)] {
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
    fn sampling_matches_numpy_arange() {
        // np.arange(0, 12, 12/8).astype(int) = [0, 1, 3, 4, 6, 7, 9, 10]
        assert_eq!(
            VideoLlavaProcessor::sample_indices(12, 8),
            vec![0, 1, 3, 4, 6, 7, 9, 10]
        );
        assert_eq!(
            VideoLlavaProcessor::sample_indices(5, 8),
            vec![0, 1, 2, 3, 4]
        );
        assert_eq!(
            VideoLlavaProcessor::sample_indices(100, 8),
            vec![0, 12, 25, 37, 50, 62, 75, 87]
        );
    }

    #[test]
    fn ops_read_processor_configs() {
        let v = serde_json::json!({"size": {"shortest_edge": 40}, "crop_size": 32,
            "resample": 3, "image_mean": [0.5, 0.5, 0.5], "image_std": [0.5, 0.5, 0.5]});
        let o = ImageOps::from_json(&v, Arith::Torch).unwrap();
        assert_eq!(o.resize, Some(ResizeTo::ShortestEdge(40)));
        assert_eq!(o.crop, Some((32, 32)));
        assert_eq!(o.output_dims(64, 48), (32, 32));
        let e = ImageOps::from_json(&serde_json::json!({"resample": 1}), Arith::Pil).unwrap_err();
        assert!(e.to_string().contains("resample"), "{e}");
        let e = ImageOps::from_json(
            &serde_json::json!({"size": {"shortest_edge": 4, "longest_edge": 9}}),
            Arith::Pil,
        )
        .unwrap_err();
        assert!(e.to_string().contains("longest_edge"), "{e}");
        let no = ImageOps::from_json(
            &serde_json::json!({"do_center_crop": false, "do_resize": false}),
            Arith::Pil,
        )
        .unwrap();
        assert_eq!(no.output_dims(7, 5), (7, 5));
    }

    #[test]
    fn normalisation_orders() {
        let t = ImageOps::clip_default(Arith::Torch);
        let p = ImageOps::clip_default(Arith::Pil);
        let img = [0u8, 128, 255];
        let a = t.to_pixel_values(&img, 1, 1);
        let b = p.to_pixel_values(&img, 1, 1);
        for c in 0..3 {
            let want = ([0.0, 128.0, 255.0][c] / 255.0 - OPENAI_CLIP_MEAN[c]) / OPENAI_CLIP_STD[c];
            assert!((a[c] as f64 - want).abs() < 1e-5);
            assert!((b[c] as f64 - want).abs() < 1e-5);
        }
    }
}
