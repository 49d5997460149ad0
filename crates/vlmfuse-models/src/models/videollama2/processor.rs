//! VideoLLaMA2's processor as its repository runs it (`videollama2/mm_utils.py` and
//! `mm_infer`): `frame_sample`'s uniform choice of `num_frames` frames, `expand2square` with the
//! processor's mean colour when the config says `pad`, the tower's `CLIPImageProcessor`
//! (Pillow's arithmetic, as transformers 4.40 runs it), the tokenizer's chat template with the
//! repository's system prompt, and `tokenizer_multimodal_token`: the prompt split at `<video>`,
//! each piece tokenized without special tokens, and the visual tokens in between.

use tokenizers::Tokenizer;

use super::config::{AspectRatio, VideoLlama2Config, MAX_FRAMES};
use crate::chat_template::{ChatTemplate, Message};
use crate::imaging::{Arith, ImageProcessor};
use crate::models::video_llava::processor::{ids_of, token_str, EncodedBatch, VideoPixels};
use crate::weights::WeightSource;
use crate::{FrameRef, ModelError};

pub use crate::models::common::VISUAL_TOKEN;

/// The text the repository puts before the user's turn (`mm_infer`, Mistral-based models).
pub const SYSTEM_PROMPT: &str = "<<SYS>>\nYou are a helpful, respectful and honest assistant. \
Always answer as helpfully as possible, while being safe.  Your answers should not include any \
harmful, unethical, racist, sexist, toxic, dangerous, or illegal content. Please ensure that your \
responses are socially unbiased and positive in nature.\nIf a question does not make any sense, \
or is not factually coherent, explain why instead of answering something not correct. If you \
don't know the answer to a question, please don't share false information.\n<</SYS>>";

/// transformers 4.40's `LlamaTokenizerFast.default_chat_template` (the LLaMA-2 format), what
/// `apply_chat_template` uses when `tokenizer_config.json` has no template.
pub const LLAMA2_DEFAULT_TEMPLATE: &str = "{% if messages[0]['role'] == 'system' %}\
{% set loop_messages = messages[1:] %}{% set system_message = messages[0]['content'] %}\
{% elif false == true and not '<<SYS>>' in messages[0]['content'] %}\
{% set loop_messages = messages %}{% set system_message = 'DEFAULT_SYSTEM_MESSAGE' %}\
{% else %}{% set loop_messages = messages %}{% set system_message = false %}{% endif %}\
{% for message in loop_messages %}\
{% if (message['role'] == 'user') != (loop.index0 % 2 == 0) %}\
{{ raise_exception('Conversation roles must alternate user/assistant/user/assistant/...') }}\
{% endif %}\
{% if loop.index0 == 0 and system_message != false %}\
{% set content = '<<SYS>>\\n' + system_message + '\\n<</SYS>>\\n\\n' + message['content'] %}\
{% else %}{% set content = message['content'] %}{% endif %}\
{% if message['role'] == 'user' %}{{ bos_token + '[INST] ' + content.strip() + ' [/INST]' }}\
{% elif message['role'] == 'system' %}{{ '<<SYS>>\\n' + content.strip() + '\\n<</SYS>>\\n\\n' }}\
{% elif message['role'] == 'assistant' %}{{ ' '  + content.strip() + ' ' + eos_token }}\
{% endif %}{% endfor %}";

/// `chat_template` as transformers stores it: a string, or a list of named templates of
/// which `default` is the one `apply_chat_template` uses.
fn template_of(v: &serde_json::Value) -> Option<String> {
    match v.get("chat_template")? {
        serde_json::Value::String(s) => Some(s.clone()),
        serde_json::Value::Array(a) => a
            .iter()
            .find(|t| t.get("name").and_then(|n| n.as_str()) == Some("default"))
            .and_then(|t| t.get("template"))
            .and_then(|t| t.as_str())
            .map(str::to_string),
        _ => None,
    }
}

pub struct VideoLlama2Processor {
    pub image: ImageProcessor,
    pub aspect_ratio: AspectRatio,
    pub num_frames: usize,
    tokenizer: Tokenizer,
    template: ChatTemplate,
    /// Whether the template came from the checkpoint (else the LLaMA-2 default).
    pub own_template: bool,
    bos: String,
    eos: String,
    pub pad_token_id: u32,
    pub eos_token_ids: Vec<u32>,
    /// The system turn (the repository's, for its Mistral models).
    pub system: Option<String>,
}

impl VideoLlama2Processor {
    /// `source` is the checkpoint (tokenizer, template, generation config), `preprocessor` the
    /// tower's `preprocessor_config.json` (the repository takes the processor from the tower).
    pub fn load(
        source: &WeightSource,
        cfg: &VideoLlama2Config,
        preprocessor: &serde_json::Value,
    ) -> Result<Self, ModelError> {
        let image = ImageProcessor::from_json(preprocessor, Arith::Pil)?;
        let path = source.resolve("tokenizer.json")?;
        // transformers 4.40 reads a Llama-style `tokenizer.json` as written (no rebuild).
        let tokenizer = Tokenizer::from_file(&path).map_err(|e| ModelError::BadWeights {
            path: path.clone(),
            reason: e.to_string(),
        })?;
        let tc: serde_json::Value = match source.resolve_optional("tokenizer_config.json")? {
            Some(_) => source.read_json("tokenizer_config.json")?,
            None => serde_json::json!({}),
        };
        let (src, own_template) = match template_of(&tc) {
            Some(t) => (t, true),
            None => (LLAMA2_DEFAULT_TEMPLATE.to_string(), false),
        };
        let template = ChatTemplate::new(&src)?;
        let bos = token_str(tc.get("bos_token")).unwrap_or_else(|| "<s>".into());
        let eos = token_str(tc.get("eos_token")).unwrap_or_else(|| "</s>".into());
        let unk = token_str(tc.get("unk_token")).unwrap_or_else(|| "<unk>".into());
        // `model_init`: pad = unk when the tokenizer has none.
        let pad = token_str(tc.get("pad_token")).unwrap_or(unk);
        let pad_token_id = tokenizer.token_to_id(&pad).unwrap_or(0);
        let mut eos_token_ids = Vec::new();
        if source.resolve_optional("generation_config.json")?.is_some() {
            let g: serde_json::Value = source.read_json("generation_config.json")?;
            eos_token_ids.extend(ids_of(g.get("eos_token_id")));
        }
        // The repository stops on the tokenizer's EOS (`KeywordsStoppingCriteria`).
        if let Some(id) = tokenizer.token_to_id(&eos) {
            if !eos_token_ids.contains(&id) {
                eos_token_ids.push(id);
            }
        }
        Ok(Self {
            image,
            aspect_ratio: cfg.aspect_ratio,
            num_frames: cfg.num_frames,
            tokenizer,
            template,
            own_template,
            bos,
            eos,
            pad_token_id,
            eos_token_ids,
            system: Some(SYSTEM_PROMPT.to_string()),
        })
    }

    pub fn tokenizer(&self) -> &Tokenizer {
        &self.tokenizer
    }

    /// `frame_sample(duration, mode='uniform')`: the middle of each of `n` equal segments of
    /// `[0, total - 1]`, rounded (`np.round(x + 1e-6)`, half to even).
    pub fn sample_indices(total: usize, n: usize) -> Vec<usize> {
        if total == 0 || n == 0 {
            return Vec::new();
        }
        let seg = (total as f64 - 1.0) / n as f64;
        (0..n)
            .map(|i| {
                let mid = (seg * i as f64 + seg * (i + 1) as f64) / 2.0 + 1e-6;
                (mid.round_ties_even() as usize).min(total - 1)
            })
            .collect()
    }

    /// The presentation times of the frames the repository's `process_video` decodes from a
    /// clip of `duration_s` at `fps` (its frame count as a container reports it).
    pub fn frame_times(&self, duration_s: f64, fps: f64) -> Option<Vec<f64>> {
        if !(duration_s > 0.0 && fps > 0.0) {
            return None;
        }
        let total = ((duration_s * fps).round() as usize).max(1);
        Some(
            Self::sample_indices(total, self.num_frames)
                .into_iter()
                .map(|i| i as f64 / fps)
                .collect(),
        )
    }

    /// The frames of `frames` the processor uses: all when there are exactly `num_frames`
    /// (the reporter decoded the sampler's own), else `frame_sample`'s choice among them.
    pub fn pick<'a>(&self, frames: &'a [FrameRef<'a>]) -> Vec<FrameRef<'a>> {
        let picked: Vec<FrameRef> = if frames.len() == self.num_frames {
            frames.to_vec()
        } else {
            Self::sample_indices(frames.len(), self.num_frames)
                .into_iter()
                .map(|i| frames[i])
                .collect()
        };
        picked.into_iter().take(MAX_FRAMES).collect()
    }

    /// The fill colour of `expand2square`: `int(m * 255)` of the processor's mean.
    pub fn fill(&self) -> [u8; 3] {
        self.image.mean.map(|m| (m * 255.0) as u8)
    }

    /// `expand2square`: the frame pasted onto a square of the fill colour, centred on the
    /// short axis (offset `(long - short) // 2`).
    pub fn expand_to_square(&self, f: FrameRef) -> Option<(Vec<u8>, u32)> {
        let (w, h) = (f.width as usize, f.height as usize);
        if w == h {
            return None;
        }
        let s = w.max(h);
        let fill = self.fill();
        let mut out = Vec::with_capacity(s * s * 3);
        for _ in 0..s * s {
            out.extend_from_slice(&fill);
        }
        let (ox, oy) = if w > h {
            (0, (w - h) / 2)
        } else {
            ((h - w) / 2, 0)
        };
        for y in 0..h {
            let dst = ((y + oy) * s + ox) * 3;
            out[dst..dst + w * 3].copy_from_slice(&f.rgb[y * w * 3..(y + 1) * w * 3]);
        }
        Some((out, s as u32))
    }

    /// Picks the clip's frames and preprocesses them to `[t, 3, S, S]`.
    pub fn preprocess_video(&self, frames: &[FrameRef]) -> Result<VideoPixels, ModelError> {
        if frames.is_empty() {
            return Err(ModelError::InvalidInput("a clip with no frames".into()));
        }
        let picked = self.pick(frames);
        let mut data = Vec::new();
        let mut dims = None;
        for f in &picked {
            let (px, w, h) = match (self.aspect_ratio, self.expand_to_square(*f)) {
                (AspectRatio::Pad, Some((sq, s))) => self.image.apply(FrameRef {
                    width: s,
                    height: s,
                    rgb: &sq,
                })?,
                _ => self.image.apply(*f)?,
            };
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
            frames: picked.len(),
            height,
            width,
        })
    }

    /// The chat prompt for one user turn about one clip, as `mm_infer` builds it.
    pub fn prompt(&self, user: &str) -> Result<String, ModelError> {
        let mut messages = Vec::new();
        if let Some(s) = &self.system {
            messages.push(Message::new("system", s));
        }
        messages.push(Message::new("user", &format!("<video>\n{user}")));
        self.template.render(&messages, &self.bos, &self.eos)
    }

    /// `tokenizer_multimodal_token`: each piece between `<video>` markers tokenized on its own
    /// without special tokens, and `visual` [`VISUAL_TOKEN`]s for each marker.
    pub fn encode(&self, prompt: &str, visual: usize) -> Result<Vec<u32>, ModelError> {
        let mut ids = Vec::new();
        for (i, piece) in prompt.split("<video>").enumerate() {
            if i > 0 {
                ids.extend(std::iter::repeat_n(VISUAL_TOKEN, visual));
            }
            let enc = self
                .tokenizer
                .encode(piece, false)
                .map_err(|e| ModelError::InvalidInput(format!("tokenizer: {e}")))?;
            ids.extend_from_slice(enc.get_ids());
        }
        Ok(ids)
    }

    /// Left-pads rows to one length (rows of one batch share the prompt and frame count, so
    /// they are equal in practice).
    pub fn pad_left(&self, rows: Vec<Vec<u32>>) -> EncodedBatch {
        crate::models::common::pad_left(rows, self.pad_token_id)
    }

    pub fn decode(&self, ids: &[u32], skip_special: bool) -> Result<String, ModelError> {
        crate::models::common::decode(&self.tokenizer, ids, skip_special)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn uniform_sampling_matches_frame_sample() {
        // videollama2.mm_utils.frame_sample(100, 'uniform', num_frames=8)
        assert_eq!(
            VideoLlama2Processor::sample_indices(100, 8),
            vec![6, 19, 31, 43, 56, 68, 80, 93]
        );
        // The same count picks every frame.
        assert_eq!(
            VideoLlama2Processor::sample_indices(8, 8),
            (0..8).collect::<Vec<_>>()
        );
        // Fewer frames than asked: repeats, as the repository does.
        assert_eq!(
            VideoLlama2Processor::sample_indices(3, 8),
            vec![0, 0, 1, 1, 1, 1, 2, 2]
        );
        assert_eq!(
            VideoLlama2Processor::sample_indices(16, 8),
            vec![1, 3, 5, 7, 8, 10, 12, 14]
        );
    }
}
