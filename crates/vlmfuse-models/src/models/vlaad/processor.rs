//! VLAAD's processor as Video-LLaMA runs it for a video (`Chat.upload_video_without_audio`,
//! `load_video`, `AlproVideoEvalProcessor`): `n_frms` frames picked by
//! `np.arange(0, n, n / n_frms)`, each decoded at `img_size × img_size` (decord scales while it
//! decodes, aspect not kept), then `/255` and the CLIP mean/std; the LLaMA-2 conversation with
//! the user turn `<Video><ImageHere></Video> The video contains N frames sampled at … seconds.
//! <prompt>`, split at `<ImageHere>` with BOS on the first piece only.

use tokenizers::Tokenizer;

use super::config::VlaadConfig;
use crate::imaging::{Arith, Resample, Resizer, OPENAI_CLIP_MEAN, OPENAI_CLIP_STD};
use crate::models::video_llava::processor::{EncodedBatch, VideoLlavaProcessor};
use crate::{FrameRef, ModelError};

pub use crate::models::common::VISUAL_TOKEN;

/// One clip's pixels, `[t, 3, S, S]`.
#[derive(Debug, Clone, PartialEq)]
pub struct ClipPixels {
    pub data: Vec<f32>,
    pub frames: usize,
    pub size: usize,
    /// The presentation time of each frame, for the prompt.
    pub times: Vec<f64>,
}

pub struct VlaadProcessor {
    tokenizer: Tokenizer,
    pub n_frms: usize,
    pub img_size: usize,
    pub system: String,
    pub eos_token_ids: Vec<u32>,
    pub pad_token_id: u32,
    table: [[f32; 256]; 3],
}

impl VlaadProcessor {
    pub fn new(
        tokenizer: Tokenizer,
        cfg: &VlaadConfig,
        eos_token_ids: Vec<u32>,
        pad_token_id: u32,
    ) -> Self {
        let mut table = [[0f32; 256]; 3];
        for (c, row) in table.iter_mut().enumerate() {
            let (m, s) = (OPENAI_CLIP_MEAN[c] as f32, OPENAI_CLIP_STD[c] as f32);
            for (v, out) in row.iter_mut().enumerate() {
                // ToTensorVideo (x / 255) then NormalizeVideo ((x - m) / s), in f32.
                *out = (v as f32 / 255.0 - m) / s;
            }
        }
        Self {
            tokenizer,
            n_frms: cfg.n_frms,
            img_size: cfg.img_size,
            system: cfg.system.clone(),
            eos_token_ids,
            pad_token_id,
            table,
        }
    }

    pub fn tokenizer(&self) -> &Tokenizer {
        &self.tokenizer
    }

    /// `load_video`'s choice: `np.arange(0, n, n / min(n_frms, n)).astype(int)`.
    pub fn sample_indices(&self, total: usize) -> Vec<usize> {
        VideoLlavaProcessor::sample_indices(total, self.n_frms.min(total))
    }

    /// The presentation times of those frames in a clip of `duration_s` at `fps`.
    pub fn frame_times(&self, duration_s: f64, fps: f64) -> Option<Vec<f64>> {
        if !(duration_s > 0.0 && fps > 0.0) {
            return None;
        }
        let total = ((duration_s * fps).round() as usize).max(1);
        Some(
            self.sample_indices(total)
                .into_iter()
                .map(|i| i as f64 / fps)
                .collect(),
        )
    }

    /// The frames used (all when there are `n_frms` or fewer: the reporter decoded the
    /// sampler's own) as normalised pixels. Frames not at `img_size²` are scaled to it
    /// (bilinear; decord scales with FFmpeg's scaler while decoding, which the service's
    /// decoder reproduces when it decodes the frames itself).
    pub fn preprocess(&self, frames: &[FrameRef], times: &[f64]) -> Result<ClipPixels, ModelError> {
        if frames.is_empty() {
            return Err(ModelError::InvalidInput("a clip with no frames".into()));
        }
        let idx: Vec<usize> = if frames.len() <= self.n_frms {
            (0..frames.len()).collect()
        } else {
            self.sample_indices(frames.len())
        };
        let s = self.img_size;
        let plane = s * s;
        let mut data = vec![0f32; idx.len() * 3 * plane];
        let mut resizer = Resizer::new();
        let mut buf = Vec::new();
        for (k, &i) in idx.iter().enumerate() {
            let f = frames[i];
            f.validate()?;
            let rgb: &[u8] = if (f.width as usize, f.height as usize) == (s, s) {
                f.rgb
            } else {
                resizer.resize_crop(f, (s, s), None, Resample::Bilinear, Arith::Torch, &mut buf)?;
                &buf
            };
            let out = &mut data[k * 3 * plane..(k + 1) * 3 * plane];
            for p in 0..plane {
                for c in 0..3 {
                    out[c * plane + p] = self.table[c][rgb[p * 3 + c] as usize];
                }
            }
        }
        Ok(ClipPixels {
            data,
            frames: idx.len(),
            size: s,
            times: idx
                .iter()
                .map(|&i| times.get(i).copied().unwrap_or(0.0))
                .collect(),
        })
    }

    /// The conversation text for one clip (`conv_llava_llama_2` with the demo's system turn).
    pub fn prompt(&self, user: &str, times: &[f64]) -> String {
        let secs: Vec<String> = times.iter().map(|t| format!("{:.1}", t)).collect();
        let msg = format!(
            "The video contains {} frames sampled at {} seconds. ",
            times.len(),
            secs.join(", ")
        );
        // Chat.ask joins the question to the video turn with a space.
        let turn = format!("<Video><ImageHere></Video> {msg} {user}");
        format!(
            "[INST] <<SYS>>\n{}\n<</SYS>>\n\n{turn} [/INST]",
            self.system
        )
    }

    /// `get_context_emb`: the pieces around `<ImageHere>` tokenized on their own, BOS on the
    /// first, `visual` [`VISUAL_TOKEN`]s between.
    pub fn encode(&self, prompt: &str, visual: usize) -> Result<Vec<u32>, ModelError> {
        let mut ids = Vec::new();
        for (i, piece) in prompt.split("<ImageHere>").enumerate() {
            if i > 0 {
                ids.extend(std::iter::repeat_n(VISUAL_TOKEN, visual));
            }
            let enc = self
                .tokenizer
                .encode(piece, i == 0)
                .map_err(|e| ModelError::InvalidInput(format!("tokenizer: {e}")))?;
            ids.extend_from_slice(enc.get_ids());
        }
        Ok(ids)
    }

    pub fn pad_left(&self, rows: Vec<Vec<u32>>) -> EncodedBatch {
        crate::models::common::pad_left(rows, self.pad_token_id)
    }

    pub fn decode(&self, ids: &[u32], skip_special: bool) -> Result<String, ModelError> {
        crate::models::common::decode(&self.tokenizer, ids, skip_special)
    }
}
