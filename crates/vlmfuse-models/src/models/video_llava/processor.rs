//! `VideoLlavaProcessor` as transformers 5.23 runs it: the video processor (torchvision on
//! uint8 tensors), the image processor (PIL), the tokenizer as transformers rebuilds it, the
//! placeholder expansion and the chat format.
//!
//! The pixels come from [`crate::imaging`]: the video processor with torch's arithmetic, the
//! image processor with Pillow's, each reproduced bit for bit.

use tokenizers::Tokenizer;

use super::config::{SelectStrategy, VideoLlavaConfig};
pub use crate::imaging::{Arith, ImageProcessor, Resample, OPENAI_CLIP_MEAN, OPENAI_CLIP_STD};
use crate::weights::WeightSource;
use crate::{FrameRef, ModelError};

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

/// A special token in `tokenizer_config.json`: a string or `{"content": …}`.
pub(crate) fn token_str(v: Option<&serde_json::Value>) -> Option<String> {
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
    use tokenizers::decoders::byte_fallback::ByteFallback;
    use tokenizers::decoders::fuse::Fuse;
    use tokenizers::decoders::sequence::Sequence as DecoderSequence;
    use tokenizers::decoders::strip::Strip;
    use tokenizers::normalizers::replace::Replace;
    use tokenizers::pre_tokenizers::metaspace::{Metaspace, PrependScheme};
    use tokenizers::processors::template::TemplateProcessing;
    use tokenizers::{DecoderWrapper, ModelWrapper, NormalizerWrapper};

    let path = source.resolve("tokenizer.json")?;
    let settings = match source.resolve_optional("tokenizer_config.json")? {
        Some(_) => TokenizerSettings::from_json(&source.read_json("tokenizer_config.json")?),
        None => TokenizerSettings::default(),
    };
    let bad = |e: String| ModelError::BadWeights {
        path: path.clone(),
        reason: e,
    };
    let mut tok = Tokenizer::from_file(&path).map_err(|e| bad(e.to_string()))?;
    let is_llama = matches!(
        settings.class.as_deref(),
        Some("LlamaTokenizer") | Some("LlamaTokenizerFast")
    );
    if is_llama {
        let ModelWrapper::BPE(mut bpe) = tok.get_model().clone() else {
            return Err(bad(
                "LlamaTokenizer needs a BPE tokenizer.json (found another model type)".into(),
            ));
        };
        bpe.fuse_unk = true;
        bpe.byte_fallback = true;
        bpe.dropout = None;
        bpe.continuing_subword_prefix = None;
        bpe.end_of_word_suffix = None;
        bpe.ignore_merges = false;
        bpe.clear_cache();
        tok.with_model(bpe);
        let add_prefix_space = settings.add_prefix_space.unwrap_or(true);
        let scheme = if !add_prefix_space {
            PrependScheme::Never
        } else if settings.legacy.unwrap_or(false) {
            PrependScheme::Always
        } else {
            PrependScheme::First
        };
        tok.with_normalizer(None::<NormalizerWrapper>)
            .map_err(|e| bad(e.to_string()))?;
        tok.with_pre_tokenizer(Some(Metaspace::new('▁', scheme, false)));
        let replace = Replace::new("▁", " ").map_err(|e| bad(e.to_string()))?;
        let mut decoders: Vec<DecoderWrapper> = vec![
            replace.into(),
            ByteFallback::new().into(),
            Fuse::new().into(),
        ];
        if add_prefix_space {
            decoders.push(Strip::new(' ', 1, 0).into());
        }
        tok.with_decoder(Some(DecoderSequence::new(decoders)));
    }
    let explicit = settings.add_bos_token.is_some() || settings.add_eos_token.is_some();
    if explicit || tok.get_post_processor().is_none() {
        // transformers' `update_post_processor`: `[bos] $A [eos]` as the flags say (Llama's
        // default is BOS on, EOS off).
        let add_bos = settings.add_bos_token.unwrap_or(is_llama);
        let add_eos = settings.add_eos_token.unwrap_or(false);
        let bos = settings.bos.clone().unwrap_or_else(|| "<s>".into());
        let eos = settings.eos.clone().unwrap_or_else(|| "</s>".into());
        let mut single: Vec<String> = Vec::new();
        let mut specials: Vec<(String, u32)> = Vec::new();
        let mut push = |t: &str, list: &mut Vec<String>| -> Result<(), ModelError> {
            let id = tok
                .token_to_id(t)
                .ok_or_else(|| bad(format!("special token `{t}` is not in the vocabulary")))?;
            if t.contains(':') || t.contains(' ') {
                return Err(bad(format!(
                    "special token `{t}` cannot appear in a template (`:` or a space)"
                )));
            }
            list.push(format!("{t}:0"));
            specials.push((t.to_string(), id));
            Ok(())
        };
        if add_bos {
            push(&bos, &mut single)?;
        }
        single.push("$A:0".into());
        if add_eos {
            push(&eos, &mut single)?;
        }
        let mut pair = single.clone();
        pair.push("$B:1".into());
        let post = TemplateProcessing::builder()
            .try_single(single)
            .map_err(bad)?
            .try_pair(pair)
            .map_err(bad)?
            .special_tokens(specials)
            .build()
            .map_err(|e| bad(e.to_string()))?;
        tok.with_post_processor(Some(post));
    }
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
    pub video: ImageProcessor,
    pub image: ImageProcessor,
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
        // Missing configs: CLIP's defaults, what both processors fall back to.
        let video = match &video_cfg {
            Some(v) => ImageProcessor::from_json(v, Arith::Torch)?,
            None => ImageProcessor::clip(224),
        };
        let image = match &image_cfg {
            Some(v) => ImageProcessor::from_json(v, Arith::Pil)?,
            None => ImageProcessor {
                arith: Arith::Pil,
                ..ImageProcessor::clip(224)
            },
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
        crate::models::common::pad_left(rows, self.pad_token_id)
    }

    pub fn decode(&self, ids: &[u32], skip_special: bool) -> Result<String, ModelError> {
        crate::models::common::decode(&self.tokenizer, ids, skip_special)
    }
}

/// `eos_token_id` may be a number or a list.
pub(crate) fn ids_of(v: Option<&serde_json::Value>) -> Vec<u32> {
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
}
