//! Qwen3-VL's video processor and prompt layout, following transformers'
//! `Qwen3VLVideoProcessor` and `Qwen3VLProcessor` with the checkpoint's own processor config:
//!
//! - frame sampling at the config's `fps` between `min_frames` and `max_frames`;
//! - `smart_resize` against a pixel budget counted over frames x height x width (`size`), or a
//!   per-frame cap when `cap_pixels_per_frame` is set;
//! - antialiased bicubic resizing **to uint8**, bit-exact with torchvision's CPU kernel
//!   ([`crate::imaging`], torch arithmetic), then the fused rescale-and-normalise in f32;
//! - patch rows in the order the vision tower's 2x2 merger expects;
//! - the prompt: per temporal patch group `<{t:.1f} seconds><|vision_start|>` + one
//!   `<|video_pad|>` per merged token + `<|vision_end|>`, `t` the mean time of the group.

use std::path::Path;

use serde_json::Value;
use tokenizers::Tokenizer;

use super::{Config, Sequence, VideoInput};
use crate::imaging::{Arith, Normalize, Resample, Resizer};
use crate::weights::WeightSource;
use crate::{FrameRef, ModelError};

fn bad(file: &str, msg: impl std::fmt::Display) -> ModelError {
    ModelError::BadConfig(format!("{file}: {msg}"))
}

/// Every setting of `video_preprocessor_config.json` the processing depends on, with
/// `Qwen3VLVideoProcessor`'s class defaults for the ones a checkpoint leaves out.
#[derive(Debug, Clone, PartialEq)]
pub struct VideoProcessorConfig {
    /// Pixel budget of a whole clip (frames x height x width after resizing): `size`'s
    /// `shortest_edge` and `longest_edge` (transformers' names; they are areas, not edges).
    pub min_pixels: usize,
    pub max_pixels: usize,
    pub patch_size: usize,
    pub temporal_patch_size: usize,
    pub merge_size: usize,
    pub image_mean: [f32; 3],
    pub image_std: [f32; 3],
    pub do_resize: bool,
    pub do_rescale: bool,
    pub rescale_factor: f64,
    pub do_normalize: bool,
    /// Sampling rate (frames per second of video) when the processor picks frames.
    pub fps: f64,
    pub min_frames: usize,
    pub max_frames: usize,
    /// A fixed frame count instead of `fps`.
    pub num_frames: Option<usize>,
    pub do_sample_frames: bool,
    /// qwen-vl-utils' per-frame cap: at most `max_video_tokens` merged tokens per frame.
    pub cap_pixels_per_frame: bool,
    pub max_video_tokens: usize,
}

impl Default for VideoProcessorConfig {
    fn default() -> Self {
        Self {
            min_pixels: 128 * 32 * 32,
            max_pixels: 32 * 32 * 768,
            patch_size: 16,
            temporal_patch_size: 2,
            merge_size: 2,
            image_mean: [0.5; 3],
            image_std: [0.5; 3],
            do_resize: true,
            do_rescale: true,
            rescale_factor: 1.0 / 255.0,
            do_normalize: true,
            fps: 2.0,
            min_frames: 4,
            max_frames: 768,
            num_frames: None,
            do_sample_frames: true,
            cap_pixels_per_frame: false,
            max_video_tokens: 768,
        }
    }
}

impl VideoProcessorConfig {
    /// Parses a processor config; `file` names it in errors.
    pub fn from_json(v: &Value, file: &str) -> Result<Self, ModelError> {
        let o = v
            .as_object()
            .ok_or_else(|| bad(file, "not a JSON object"))?;
        let mut c = Self::default();
        let num = |k: &str| -> Result<Option<f64>, ModelError> {
            match o.get(k) {
                None | Some(Value::Null) => Ok(None),
                Some(x) => x
                    .as_f64()
                    .map(Some)
                    .ok_or_else(|| bad(file, format!("`{k}` = {x} is not a number"))),
            }
        };
        let count = |k: &str| -> Result<Option<usize>, ModelError> {
            match num(k)? {
                Some(x) if x >= 0.0 && x.fract() == 0.0 => Ok(Some(x as usize)),
                Some(x) => Err(bad(file, format!("`{k}` = {x} is not a whole number"))),
                None => Ok(None),
            }
        };
        let flag = |k: &str| -> Result<Option<bool>, ModelError> {
            match o.get(k) {
                None | Some(Value::Null) => Ok(None),
                Some(Value::Bool(b)) => Ok(Some(*b)),
                Some(x) => Err(bad(file, format!("`{k}` = {x} is not a boolean"))),
            }
        };
        let triple = |k: &str| -> Result<Option<[f32; 3]>, ModelError> {
            match o.get(k) {
                None | Some(Value::Null) => Ok(None),
                Some(Value::Number(n)) => Ok(n.as_f64().map(|x| [x as f32; 3])),
                Some(Value::Array(a)) if a.len() == 3 && a.iter().all(Value::is_number) => {
                    let f = |i: usize| a[i].as_f64().unwrap_or_default() as f32;
                    Ok(Some([f(0), f(1), f(2)]))
                }
                Some(x) => Err(bad(file, format!("`{k}` = {x} is not three numbers"))),
            }
        };
        // Qwen2-VL-era files put the budget at the top level.
        if let Some(x) = count("min_pixels")? {
            c.min_pixels = x;
        }
        if let Some(x) = count("max_pixels")? {
            c.max_pixels = x;
        }
        match o.get("size") {
            None | Some(Value::Null) => {}
            Some(Value::Object(s)) => {
                for (k, slot) in [
                    ("shortest_edge", &mut c.min_pixels),
                    ("longest_edge", &mut c.max_pixels),
                ] {
                    match s.get(k).and_then(Value::as_u64) {
                        Some(x) => *slot = x as usize,
                        None if s.contains_key(k) => {
                            return Err(bad(file, format!("`size.{k}` is not a whole number")))
                        }
                        None => {}
                    }
                }
                if s.contains_key("height") || s.contains_key("width") {
                    return Err(bad(
                        file,
                        "a fixed `size` (height/width) is not how Qwen3-VL resizes; expected \
                         shortest_edge/longest_edge pixel budgets",
                    ));
                }
            }
            Some(x) => return Err(bad(file, format!("`size` = {x} is not an object"))),
        }
        for (k, slot) in [
            ("patch_size", &mut c.patch_size),
            ("temporal_patch_size", &mut c.temporal_patch_size),
            ("merge_size", &mut c.merge_size),
            ("min_frames", &mut c.min_frames),
            ("max_frames", &mut c.max_frames),
            ("max_video_tokens", &mut c.max_video_tokens),
        ] {
            if let Some(x) = count(k)? {
                *slot = x;
            }
        }
        c.num_frames = count("num_frames")?;
        if let Some(x) = triple("image_mean")? {
            c.image_mean = x;
        }
        if let Some(x) = triple("image_std")? {
            c.image_std = x;
        }
        for (k, slot) in [
            ("do_resize", &mut c.do_resize),
            ("do_rescale", &mut c.do_rescale),
            ("do_normalize", &mut c.do_normalize),
            ("do_sample_frames", &mut c.do_sample_frames),
            ("cap_pixels_per_frame", &mut c.cap_pixels_per_frame),
        ] {
            if let Some(x) = flag(k)? {
                *slot = x;
            }
        }
        if let Some(x) = num("rescale_factor")? {
            c.rescale_factor = x;
        }
        if let Some(x) = num("fps")? {
            c.fps = x;
        }
        // PIL's enum: 3 = BICUBIC, the class default and what every Qwen checkpoint uses.
        match count("resample")? {
            None | Some(3) => {}
            Some(r) => {
                return Err(bad(
                    file,
                    format!("resample = {r}: only bicubic (3) is implemented"),
                ))
            }
        }
        c.validate(file)?;
        Ok(c)
    }

    fn validate(&self, file: &str) -> Result<(), ModelError> {
        for (k, x) in [
            ("patch_size", self.patch_size),
            ("temporal_patch_size", self.temporal_patch_size),
            ("merge_size", self.merge_size),
            ("max_frames", self.max_frames),
        ] {
            if x == 0 {
                return Err(bad(file, format!("`{k}` must be positive")));
            }
        }
        if self.min_pixels > self.max_pixels {
            return Err(bad(
                file,
                format!(
                    "pixel budget {}..{} is empty",
                    self.min_pixels, self.max_pixels
                ),
            ));
        }
        if self.min_frames > self.max_frames {
            return Err(bad(
                file,
                format!(
                    "min_frames {} > max_frames {}",
                    self.min_frames, self.max_frames
                ),
            ));
        }
        if !(self.fps > 0.0 && self.fps.is_finite()) {
            return Err(bad(file, format!("fps {} must be positive", self.fps)));
        }
        if self.image_std.contains(&0.0) {
            return Err(bad(file, "image_std has a zero"));
        }
        Ok(())
    }

    /// The checkpoint's video processor config, resolved as transformers resolves it:
    /// `processor_config.json`'s nested `video_processor` (what transformers 5.23's
    /// `save_pretrained` writes), else `video_preprocessor_config.json`, else
    /// `preprocessor_config.json` (where older checkpoints keep both), else the class defaults.
    pub fn from_source(src: &WeightSource) -> Result<Self, ModelError> {
        const PROC: &str = "processor_config.json";
        if src.resolve_optional(PROC)?.is_some() {
            let v: Value = src.read_json(PROC)?;
            if let Some(vp) = v.get("video_processor").filter(|x| x.is_object()) {
                return Self::from_json(vp, "processor_config.json (video_processor)");
            }
        }
        for f in ["video_preprocessor_config.json", "preprocessor_config.json"] {
            if src.resolve_optional(f)?.is_some() {
                let v: Value = src.read_json(f)?;
                return Self::from_json(&v, f);
            }
        }
        Ok(Self::default())
    }

    /// Pixels per side of one merged token.
    pub fn factor(&self) -> usize {
        self.patch_size * self.merge_size
    }
}

/// Python's `round` (halves to even).
fn py_round(x: f64) -> f64 {
    x.round_ties_even()
}

/// `smart_resize` of `Qwen3VLVideoProcessor`: both sides a multiple of `factor`, the clip's
/// total pixels (`frames x h x w`, frames rounded to the temporal patch) within
/// `[min_pixels, max_pixels]`, aspect ratio kept as well as possible. Returns `(height, width)`.
///
/// The reference raises for fewer frames than `temporal_factor`; here such a clip is costed as
/// if its last frame were repeated, which is what patching it does anyway.
pub fn smart_resize(
    num_frames: usize,
    height: usize,
    width: usize,
    temporal_factor: usize,
    factor: usize,
    min_pixels: usize,
    max_pixels: usize,
) -> Result<(usize, usize), ModelError> {
    if height == 0 || width == 0 || factor == 0 || temporal_factor == 0 {
        return Err(ModelError::InvalidInput(format!(
            "cannot resize a {width}x{height} frame to a multiple of {factor}"
        )));
    }
    let num_frames = num_frames.max(temporal_factor) as f64;
    let f = factor as f64;
    let (mut h, mut w) = (height as f64, width as f64);
    if height < factor || width < factor {
        let scale = (f / h).max(f / w);
        h = (h * scale).trunc();
        w = (w * scale).trunc();
    }
    if h.max(w) / h.min(w) > 200.0 {
        return Err(ModelError::InvalidInput(format!(
            "aspect ratio of a {width}x{height} frame is above 200"
        )));
    }
    let tf = temporal_factor as f64;
    let mut h_bar = py_round(h / f) * f;
    let mut w_bar = py_round(w / f) * f;
    let t_bar = py_round(num_frames / tf) * tf;
    if t_bar * h_bar * w_bar > max_pixels as f64 {
        let beta = (num_frames * h * w / max_pixels as f64).sqrt();
        h_bar = f.max((h / beta / f).floor() * f);
        w_bar = f.max((w / beta / f).floor() * f);
    } else if t_bar * h_bar * w_bar < min_pixels as f64 {
        let beta = (min_pixels as f64 / (num_frames * h * w)).sqrt();
        h_bar = (h * beta / f).ceil() * f;
        w_bar = (w * beta / f).ceil() * f;
    }
    Ok((h_bar as usize, w_bar as usize))
}

/// A processed clip: the vision tower's input and what the prompt needs to describe it.
#[derive(Debug, Clone, PartialEq)]
pub struct ProcessedVideo {
    pub input: VideoInput,
    /// Size every frame was resized to, `(height, width)`.
    pub resized: (usize, usize),
    /// Mean time (seconds) of each temporal patch group, as the prompt states it.
    pub timestamps: Vec<f64>,
}

impl ProcessedVideo {
    /// `<|video_pad|>` placeholders per temporal group.
    pub fn tokens_per_group(&self, merge: usize) -> usize {
        self.input.grid_thw[1] * self.input.grid_thw[2] / (merge * merge)
    }
}

/// The video processor of one checkpoint.
#[derive(Debug, Clone, PartialEq)]
pub struct VideoProcessor {
    pub config: VideoProcessorConfig,
}

impl VideoProcessor {
    pub fn new(config: VideoProcessorConfig) -> Self {
        Self { config }
    }

    /// Which of a clip's `total` decoded frames (at `video_fps`) the processor keeps:
    /// `fps` per second (or `num_frames`), clamped to `[min_frames, max_frames]` and to the
    /// clip, spread evenly with `np.linspace(...).round()`.
    pub fn sample_indices(&self, total: usize, video_fps: f64) -> Vec<usize> {
        let c = &self.config;
        if total == 0 {
            return Vec::new();
        }
        let n = match c.num_frames {
            Some(n) => n.min(c.max_frames),
            None => {
                let fps = if video_fps > 0.0 && video_fps.is_finite() {
                    video_fps
                } else {
                    24.0
                };
                let n = (total as f64 / fps * c.fps) as usize;
                n.max(c.min_frames).min(c.max_frames).min(total)
            }
        };
        linspace_round(total - 1, n)
    }

    /// Output size for `frames` frames of `height x width`, with the per-frame cap if set.
    pub fn target_size(
        &self,
        frames: usize,
        height: usize,
        width: usize,
    ) -> Result<(usize, usize), ModelError> {
        let c = &self.config;
        let factor = c.factor();
        let mut max_pixels = c.max_pixels;
        if c.cap_pixels_per_frame {
            let n = frames.max(1);
            let cap = c.max_video_tokens * factor * factor;
            let per_frame = cap
                .min(c.max_pixels / n)
                .max((c.min_pixels as f64 * 1.05) as usize);
            max_pixels = per_frame * n;
        }
        smart_resize(
            frames,
            height,
            width,
            c.temporal_patch_size,
            factor,
            c.min_pixels,
            max_pixels,
        )
    }

    /// Resizes, normalises and patches `frames` (all of one size; `timestamps` in seconds, one
    /// per frame). An odd count is padded by repeating the last frame, as the reference does.
    pub fn process(
        &self,
        frames: &[FrameRef],
        timestamps: &[f64],
    ) -> Result<ProcessedVideo, ModelError> {
        let c = &self.config;
        let first = frames
            .first()
            .ok_or_else(|| ModelError::InvalidInput("clip has no frames".into()))?;
        if timestamps.len() != frames.len() {
            return Err(ModelError::InvalidInput(format!(
                "{} timestamps for {} frames",
                timestamps.len(),
                frames.len()
            )));
        }
        for (i, f) in frames.iter().enumerate() {
            f.validate()?;
            if (f.width, f.height) != (first.width, first.height) {
                return Err(ModelError::InvalidInput(format!(
                    "frame {i} is {}x{}, frame 0 is {}x{}: a clip's frames must share a size",
                    f.width, f.height, first.width, first.height
                )));
            }
        }
        if let Some(t) = timestamps.iter().find(|t| !t.is_finite()) {
            return Err(ModelError::InvalidInput(format!("frame timestamp {t}")));
        }
        let (ps, tps, ms) = (c.patch_size, c.temporal_patch_size, c.merge_size);
        let (in_h, in_w) = (first.height as usize, first.width as usize);
        let (rh, rw) = if c.do_resize {
            self.target_size(frames.len(), in_h, in_w)?
        } else {
            (in_h, in_w)
        };
        if rh % (ps * ms) != 0 || rw % (ps * ms) != 0 {
            return Err(ModelError::InvalidInput(format!(
                "frames of {rw}x{rh} are not a multiple of {} (do_resize is off)",
                ps * ms
            )));
        }
        // Rescale + normalise as the torchvision processors fuse them.
        let table = Normalize {
            rescale: c.do_rescale.then_some(c.rescale_factor),
            mean: c.image_mean.map(f64::from),
            std: c.image_std.map(f64::from),
            normalize: c.do_normalize,
            arith: Arith::Torch,
        }
        .table();
        let mut resizer = Resizer::new();
        let mut rgb = Vec::new();
        let mut planes: Vec<Vec<f32>> = Vec::with_capacity(frames.len() + tps);
        for f in frames {
            resizer.resize_crop(
                *f,
                (rw, rh),
                None,
                Resample::Bicubic,
                Arith::Torch,
                &mut rgb,
            )?;
            let mut chw = vec![0f32; 3 * rh * rw];
            Normalize::hwc_to_chw(&table, &rgb, &mut chw);
            planes.push(chw);
        }
        let mut times = timestamps.to_vec();
        while !planes.len().is_multiple_of(tps) {
            planes.push(planes.last().expect("non-empty").clone());
            times.push(*times.last().expect("non-empty"));
        }
        let (gt, gh, gw) = (planes.len() / tps, rh / ps, rw / ps);
        let mut data = Vec::with_capacity(gt * gh * gw * 3 * tps * ps * ps);
        // HF's view (t, tps, C, h/ms, ms, ps, w/ms, ms, ps) permuted to
        // (t, h/ms, w/ms, ms, ms, C, tps, ps, ps).
        for t in 0..gt {
            for bh in 0..gh / ms {
                for bw in 0..gw / ms {
                    for mh in 0..ms {
                        for mw in 0..ms {
                            let y0 = (bh * ms + mh) * ps;
                            let x0 = (bw * ms + mw) * ps;
                            for ch in 0..3 {
                                for tp in 0..tps {
                                    let plane = &planes[t * tps + tp][ch * rh * rw..];
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
        let timestamps = times
            .chunks(tps)
            .map(|g| (g[0] + g[g.len() - 1]) / 2.0)
            .collect();
        Ok(ProcessedVideo {
            input: VideoInput {
                pixel_values: data,
                grid_thw: [gt, gh, gw],
            },
            resized: (rh, rw),
            timestamps,
        })
    }
}

/// `np.linspace(0, last, n).round()` (numpy's formula, halves to even).
fn linspace_round(last: usize, n: usize) -> Vec<usize> {
    match n {
        0 => Vec::new(),
        1 => vec![0],
        _ => {
            let step = last as f64 / (n - 1) as f64;
            (0..n)
                .map(|i| {
                    if i == n - 1 {
                        last
                    } else {
                        (i as f64 * step).round_ties_even() as usize
                    }
                })
                .collect()
        }
    }
}

/// Tokenizer, video processor and the special tokens of one checkpoint: turns frames and a
/// question into a [`Sequence`] for [`super::Qwen3Vl::prefill`].
pub struct Qwen3VlProcessor {
    pub video: VideoProcessor,
    tokenizer: Tokenizer,
    video_token_id: u32,
    merge: usize,
    video_pad: String,
    vision_start: String,
    vision_end: String,
    eos: Vec<u32>,
}

fn tok_err(e: impl std::fmt::Display) -> ModelError {
    ModelError::BadConfig(format!("tokenizer: {e}"))
}

impl Qwen3VlProcessor {
    /// `tokenizer.json`, the video processor config and `generation_config.json` of a
    /// checkpoint, with the special token ids from its (parsed) `config`.
    pub fn load(src: &WeightSource, config: &Config) -> Result<Self, ModelError> {
        let tok_path = src.resolve("tokenizer.json")?;
        let tokenizer = Tokenizer::from_file(&tok_path).map_err(|e| ModelError::BadWeights {
            path: tok_path.clone(),
            reason: e.to_string(),
        })?;
        let mut eos = Vec::new();
        if src.resolve_optional("generation_config.json")?.is_some() {
            let g: Value = src.read_json("generation_config.json")?;
            eos = ids_of(g.get("eos_token_id"));
        }
        let mut p = Self::new(tokenizer, VideoProcessorConfig::from_source(src)?, config)?;
        // Chat models end their turn with <|im_end|> even where configs list only <|endoftext|>.
        if let Some(id) = p.tokenizer.token_to_id("<|im_end|>") {
            eos.push(id);
        }
        eos.sort_unstable();
        eos.dedup();
        p.eos = eos;
        Ok(p)
    }

    pub fn new(
        tokenizer: Tokenizer,
        video: VideoProcessorConfig,
        config: &Config,
    ) -> Result<Self, ModelError> {
        let name = |id: u32, what: &str| -> Result<String, ModelError> {
            tokenizer.id_to_token(id).ok_or_else(|| {
                ModelError::BadConfig(format!(
                    "the tokenizer has no token {id}, which config.json names as {what}"
                ))
            })
        };
        if video.merge_size != config.vision.spatial_merge_size
            || video.patch_size != config.vision.patch_size
            || video.temporal_patch_size != config.vision.temporal_patch_size
        {
            return Err(ModelError::BadConfig(format!(
                "video processor patches {}/{}/{} (patch/temporal/merge) do not match the vision \
                 tower's {}/{}/{}",
                video.patch_size,
                video.temporal_patch_size,
                video.merge_size,
                config.vision.patch_size,
                config.vision.temporal_patch_size,
                config.vision.spatial_merge_size
            )));
        }
        Ok(Self {
            video_pad: name(config.video_token_id, "video_token_id")?,
            vision_start: name(config.vision_start_token_id, "vision_start_token_id")?,
            vision_end: name(config.vision_end_token_id, "vision_end_token_id")?,
            video_token_id: config.video_token_id,
            merge: config.vision.spatial_merge_size,
            video: VideoProcessor::new(video),
            tokenizer,
            eos: Vec::new(),
        })
    }

    pub fn tokenizer(&self) -> &Tokenizer {
        &self.tokenizer
    }

    /// Ids that end a generated answer.
    pub fn eos_ids(&self) -> &[u32] {
        &self.eos
    }

    /// The video's placeholder text: one timestamped block per temporal group.
    pub fn video_placeholder(&self, video: &ProcessedVideo) -> String {
        let n = video.tokens_per_group(self.merge);
        let mut s = String::new();
        for t in &video.timestamps {
            s.push_str(&format!("<{t:.1} seconds>"));
            s.push_str(&self.vision_start);
            for _ in 0..n {
                s.push_str(&self.video_pad);
            }
            s.push_str(&self.vision_end);
        }
        s
    }

    /// The user turn of Qwen3-VL's chat template with the video in front of the question,
    /// placeholders expanded as the processor expands them.
    pub fn prompt_text(&self, prompt: &str, video: Option<&ProcessedVideo>) -> String {
        let v = video.map(|v| self.video_placeholder(v)).unwrap_or_default();
        format!("<|im_start|>user\n{v}{prompt}<|im_end|>\n<|im_start|>assistant\n")
    }

    /// Token ids of [`prompt_text`](Self::prompt_text), checked against the video.
    pub fn prepare(
        &self,
        prompt: &str,
        video: Option<ProcessedVideo>,
    ) -> Result<Sequence, ModelError> {
        let text = self.prompt_text(prompt, video.as_ref());
        let ids = self
            .tokenizer
            .encode(text.as_str(), true)
            .map_err(tok_err)?
            .get_ids()
            .to_vec();
        let pads = ids.iter().filter(|&&t| t == self.video_token_id).count();
        let want = video
            .as_ref()
            .map(|v| v.tokens_per_group(self.merge) * v.timestamps.len())
            .unwrap_or(0);
        if pads != want {
            return Err(ModelError::InvalidInput(format!(
                "the prompt holds {pads} video placeholders after tokenizing, the video needs \
                 {want} (does the question itself contain `{}`?)",
                self.video_pad
            )));
        }
        Ok(Sequence {
            ids,
            video: video.map(|v| v.input),
        })
    }

    /// Processes frames (with their times in seconds) and the question in one go.
    pub fn prepare_frames(
        &self,
        prompt: &str,
        frames: &[FrameRef],
        timestamps: &[f64],
    ) -> Result<Sequence, ModelError> {
        let v = self.video.process(frames, timestamps)?;
        self.prepare(prompt, Some(v))
    }

    /// Text of generated ids, special tokens dropped.
    pub fn decode(&self, ids: &[u32]) -> Result<String, ModelError> {
        self.tokenizer.decode(ids, true).map_err(tok_err)
    }
}

/// `eos_token_id` may be a number or a list.
fn ids_of(v: Option<&Value>) -> Vec<u32> {
    match v {
        Some(Value::Number(n)) => n.as_u64().map(|x| vec![x as u32]).unwrap_or_default(),
        Some(Value::Array(a)) => a
            .iter()
            .filter_map(|x| x.as_u64().map(|x| x as u32))
            .collect(),
        _ => Vec::new(),
    }
}

/// Reads the processor config straight from a directory (for tools and tests).
pub fn video_config_from_dir(dir: &Path) -> Result<VideoProcessorConfig, ModelError> {
    VideoProcessorConfig::from_source(&WeightSource::local(dir))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn smart_resize_follows_the_video_budget() {
        // Under budget, rounded to the factor.
        assert_eq!(
            smart_resize(4, 30, 50, 2, 8, 2048, 32768).unwrap(),
            (32, 48)
        );
        // Over budget: shrunk over frames x h x w.
        assert_eq!(smart_resize(4, 48, 64, 2, 8, 256, 4096).unwrap(), (24, 32));
        // Smaller than one factor: scaled up first, then to the minimum budget.
        let (h, w) = smart_resize(2, 5, 6, 2, 8, 2048, 32768).unwrap();
        assert!(h % 8 == 0 && w % 8 == 0 && 2 * h * w >= 2048, "{h}x{w}");
        assert!(smart_resize(2, 1, 300, 2, 8, 1, 1 << 20).is_err());
        assert!(smart_resize(2, 0, 3, 2, 8, 1, 10).is_err());
        // One frame is costed as two.
        assert_eq!(
            smart_resize(1, 64, 64, 2, 8, 1, 8192).unwrap(),
            smart_resize(2, 64, 64, 2, 8, 1, 8192).unwrap()
        );
    }

    #[test]
    fn sampling_matches_numpy_linspace() {
        assert_eq!(linspace_round(9, 4), vec![0, 3, 6, 9]);
        assert_eq!(linspace_round(10, 4), vec![0, 3, 7, 10]);
        let vp = VideoProcessor::new(VideoProcessorConfig {
            min_frames: 2,
            max_frames: 8,
            fps: 2.0,
            ..Default::default()
        });
        // 3 s at 10 fps, 2 fps wanted: 6 frames.
        assert_eq!(vp.sample_indices(30, 10.0), vec![0, 6, 12, 17, 23, 29]);
        // Long clip: capped at max_frames.
        assert_eq!(vp.sample_indices(1000, 10.0).len(), 8);
        // Short clip: min_frames, but never more than the clip has.
        assert_eq!(vp.sample_indices(1, 30.0), vec![0]);
        assert!(vp.sample_indices(0, 30.0).is_empty());
    }

    #[test]
    fn timestamps_print_like_python() {
        // Python: f"{0.25:.1f}" == "0.2", f"{0.35:.1f}" == "0.3", f"{2.45:.1f}" == "2.5".
        let s: Vec<String> = [0.25f64, 0.75, 0.35, 2.45]
            .iter()
            .map(|t| format!("{t:.1}"))
            .collect();
        assert_eq!(s, ["0.2", "0.8", "0.3", "2.5"]);
    }

    #[test]
    fn config_reads_budget_and_refuses_unknown_resampling() {
        let c = VideoProcessorConfig::from_json(
            &serde_json::json!({"size": {"shortest_edge": 10, "longest_edge": 100},
                "patch_size": 4, "fps": 1.5, "cap_pixels_per_frame": true}),
            "x.json",
        )
        .unwrap();
        assert_eq!((c.min_pixels, c.max_pixels, c.patch_size), (10, 100, 4));
        assert!(c.cap_pixels_per_frame && c.fps == 1.5);
        let e = VideoProcessorConfig::from_json(&serde_json::json!({"resample": 2}), "x.json")
            .unwrap_err()
            .to_string();
        assert!(e.contains("bicubic") && e.contains("x.json"), "{e}");
        let e = VideoProcessorConfig::from_json(
            &serde_json::json!({"size": {"height": 224, "width": 224}}),
            "x.json",
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("shortest_edge"), "{e}");
        assert!(VideoProcessorConfig::from_json(&serde_json::json!({"fps": 0}), "x").is_err());
    }
}
