//! What a model family gives the in-process reporter, and the table of families.
//!
//! A family (Qwen3-VL, VideoLLaVA, VideoLLaMA2, VLAAD) is one folder under
//! [`crate::models`] with its config, vision and text towers, its processor and a `family.rs`
//! that implements [`Family`]: load a checkpoint, turn clips into model inputs, and the
//! model whose [`Decoder`] steps [`crate::generate`] drives. Adding one is that folder plus one line
//! in [`FAMILIES`]; nothing else matches on the architecture.

use std::any::Any;
use std::sync::atomic::AtomicBool;

use candle_core::{DType, Device, Tensor};

use crate::generate::{generate, Decoder, GenerateOptions, Generated};
use crate::weights::WeightSource;
use crate::{Frame, ModelError};

/// How a reporter loads a family.
#[derive(Debug, Clone)]
pub struct FamilyOptions {
    pub dtype: DType,
    pub device: Device,
    /// A PEFT LoRA adapter merged into the weights at load.
    pub adapter: Option<WeightSource>,
    /// Frames per clip, where the family lets the reporter choose (Qwen3-VL); a family whose
    /// processor fixes its own count refuses it.
    pub frames: Option<usize>,
    /// The user turn of the chat prompt.
    pub prompt: String,
}

/// What a prepared input looks like, for `vlmfuse describe --dump` and logs.
#[derive(Debug, Clone, Default)]
pub struct InputView {
    /// Token ids of each row (left padding included where the family pads).
    pub input_ids: Vec<Vec<u32>>,
    /// Visual placeholder tokens per row.
    pub visual_tokens: Vec<usize>,
    /// Prompt length of each row: placeholders included, padding excluded.
    pub prompt_tokens: Vec<usize>,
}

/// The vision tower's input of one row, on the CPU in f32, with its grid as JSON.
pub type Pixels = (Tensor, serde_json::Value);

/// The inputs of a family: what its model's [`Decoder`] takes.
pub type Inputs<F> = <<F as Family>::Model as Decoder>::Inputs;

/// One model family: a loaded checkpoint with its processor.
pub trait Family: Send + Sync + Sized + 'static {
    /// The model [`crate::generate`] drives (its prefill and steps).
    type Model: Decoder<Inputs: Send + 'static>;

    /// `config.json`'s `model_type`.
    const MODEL_TYPE: &'static str;

    fn model(&self) -> &Self::Model;

    /// Loads the checkpoint and its processor configs. Blocking.
    fn load(weights: &WeightSource, opts: &FamilyOptions) -> Result<Self, ModelError>;
    /// One row per clip, each with the prompt in the family's chat format. Clips are non-empty
    /// and their frames valid (checked by the caller).
    fn prepare(&self, clips: &[&[Frame]]) -> Result<Inputs<Self>, ModelError>;
    fn view(&self, inputs: &Inputs<Self>) -> InputView;
    /// Row `r`'s pixel values and grid, as the vision tower takes them.
    fn pixels(&self, inputs: &Inputs<Self>, r: usize) -> Result<Option<Pixels>, ModelError>;
    /// Ids that end an answer: `generation_config.json`'s, plus the chat turn end.
    fn eos_ids(&self) -> &[u32];
    /// Text of generated ids, special tokens dropped.
    fn decode(&self, ids: &[u32]) -> Result<String, ModelError>;
    fn dtype(&self) -> DType;
    fn device(&self) -> &Device;
    fn merged_lora_keys(&self) -> &[String];
    fn vocab_size(&self) -> usize;
    /// Frames of each clip the processor takes.
    fn frames(&self) -> usize;
    /// The presentation times of the frames the checkpoint's own sampler picks from a clip of
    /// `duration_s` at `fps`, when the family has one in force (the reporter then decodes
    /// exactly those frames and [`Family::prepare`] takes them all); `None` to take the media
    /// layer's frames.
    fn frame_times(&self, _duration_s: f64, _fps: f64) -> Option<Vec<f64>> {
        None
    }
    /// The `(width, height)` the checkpoint's own decoder scales those frames to while
    /// decoding (VLAAD's decord decodes at the model's input size); `None`: source size.
    fn frame_size(&self) -> Option<(u32, u32)> {
        None
    }
}

/// A batch prepared by some family, its type erased so the reporter holds one kind of value.
pub struct Prepared {
    model_type: &'static str,
    rows: usize,
    inner: Box<dyn Any + Send>,
}

impl Prepared {
    pub fn rows(&self) -> usize {
        self.rows
    }

    /// The family that built it.
    pub fn model_type(&self) -> &'static str {
        self.model_type
    }

    fn get<F: Family>(&self) -> Result<&Inputs<F>, ModelError> {
        self.inner.downcast_ref::<Inputs<F>>().ok_or_else(|| {
            ModelError::InvalidInput(format!(
                "inputs prepared by {} given to {}",
                self.model_type,
                F::MODEL_TYPE
            ))
        })
    }
}

/// A [`Family`] behind a trait object: what the reporter holds. Implemented for every family.
pub trait AnyFamily: Send + Sync {
    fn model_type(&self) -> &'static str;
    /// Checks the clips, then builds one row per clip.
    fn prepare(&self, clips: &[&[Frame]]) -> Result<Prepared, ModelError>;
    fn view(&self, p: &Prepared) -> Result<InputView, ModelError>;
    fn pixels(&self, p: &Prepared, r: usize) -> Result<Option<Pixels>, ModelError>;
    /// [`crate::generate::generate`] over this family.
    fn generate(
        &self,
        p: &Prepared,
        opts: &GenerateOptions,
        cancel: Option<&AtomicBool>,
    ) -> Result<Generated, ModelError>;
    fn eos_ids(&self) -> &[u32];
    fn decode(&self, ids: &[u32]) -> Result<String, ModelError>;
    fn dtype(&self) -> DType;
    fn device(&self) -> &Device;
    fn merged_lora_keys(&self) -> &[String];
    fn vocab_size(&self) -> usize;
    fn frames(&self) -> usize;
    /// [`Family::frame_times`].
    fn frame_times(&self, duration_s: f64, fps: f64) -> Option<Vec<f64>>;
    /// [`Family::frame_size`].
    fn frame_size(&self) -> Option<(u32, u32)>;
    /// The concrete family, for tests and tools that need its model or processor.
    fn as_any(&self) -> &dyn Any;
}

impl<F: Family> AnyFamily for F {
    fn model_type(&self) -> &'static str {
        F::MODEL_TYPE
    }

    fn prepare(&self, clips: &[&[Frame]]) -> Result<Prepared, ModelError> {
        if clips.is_empty() {
            return Err(ModelError::InvalidInput("an empty batch".into()));
        }
        for (i, c) in clips.iter().enumerate() {
            if c.is_empty() {
                return Err(ModelError::InvalidInput(format!("clip {i} has no frames")));
            }
            for f in c.iter() {
                f.as_ref().validate()?;
            }
        }
        let inputs = Family::prepare(self, clips)?;
        Ok(Prepared {
            model_type: F::MODEL_TYPE,
            rows: <F::Model as Decoder>::rows(&inputs),
            inner: Box::new(inputs),
        })
    }

    fn view(&self, p: &Prepared) -> Result<InputView, ModelError> {
        Ok(Family::view(self, p.get::<F>()?))
    }

    fn pixels(&self, p: &Prepared, r: usize) -> Result<Option<Pixels>, ModelError> {
        Family::pixels(self, p.get::<F>()?, r)
    }

    fn generate(
        &self,
        p: &Prepared,
        opts: &GenerateOptions,
        cancel: Option<&AtomicBool>,
    ) -> Result<Generated, ModelError> {
        generate(self.model(), p.get::<F>()?, opts, cancel)
    }

    fn eos_ids(&self) -> &[u32] {
        Family::eos_ids(self)
    }
    fn decode(&self, ids: &[u32]) -> Result<String, ModelError> {
        Family::decode(self, ids)
    }
    fn dtype(&self) -> DType {
        Family::dtype(self)
    }
    fn device(&self) -> &Device {
        Family::device(self)
    }
    fn merged_lora_keys(&self) -> &[String] {
        Family::merged_lora_keys(self)
    }
    fn vocab_size(&self) -> usize {
        Family::vocab_size(self)
    }
    fn frames(&self) -> usize {
        Family::frames(self)
    }
    fn frame_times(&self, duration_s: f64, fps: f64) -> Option<Vec<f64>> {
        Family::frame_times(self, duration_s, fps)
    }
    fn frame_size(&self) -> Option<(u32, u32)> {
        Family::frame_size(self)
    }
    fn as_any(&self) -> &dyn Any {
        self
    }
}

/// How a registered family loads: weights and options in, the family behind [`AnyFamily`].
pub type LoadFn = fn(&WeightSource, &FamilyOptions) -> Result<Box<dyn AnyFamily>, ModelError>;

/// One line of [`FAMILIES`]: a `model_type` and how to load it.
pub struct Registration {
    pub model_type: &'static str,
    pub load: LoadFn,
}

impl Registration {
    pub const fn of<F: Family>() -> Self {
        Self {
            model_type: F::MODEL_TYPE,
            load: load_boxed::<F>,
        }
    }

    /// `F` under another `model_type` its checkpoints carry (VideoLLaMA2 writes two).
    pub const fn alias<F: Family>(model_type: &'static str) -> Self {
        Self {
            model_type,
            load: load_boxed::<F>,
        }
    }
}

fn load_boxed<F: Family>(
    weights: &WeightSource,
    opts: &FamilyOptions,
) -> Result<Box<dyn AnyFamily>, ModelError> {
    Ok(Box::new(F::load(weights, opts)?))
}

/// Every family an in-process reporter can load, one line each.
pub const FAMILIES: &[Registration] = &[
    Registration::of::<super::qwen3_vl::Qwen3VlFamily>(),
    Registration::of::<super::video_llava::VideoLlavaFamily>(),
    Registration::of::<super::videollama2::VideoLlama2Family>(),
    Registration::alias::<super::videollama2::VideoLlama2Family>("videollama2_mistral"),
    Registration::of::<super::vlaad::VlaadFamily>(),
    Registration::alias::<super::vlaad::VlaadFamily>("video_llama"),
];

/// The `model_type`s of [`FAMILIES`].
pub fn supported_model_types() -> Vec<&'static str> {
    FAMILIES.iter().map(|f| f.model_type).collect()
}

/// Reads `config.json`'s `model_type` and loads that family.
pub fn load_family(
    weights: &WeightSource,
    opts: &FamilyOptions,
) -> Result<Box<dyn AnyFamily>, ModelError> {
    let raw: serde_json::Value = weights.read_json("config.json")?;
    let model_type = raw.get("model_type").and_then(|v| v.as_str());
    if let Some(reg) = FAMILIES.iter().find(|f| Some(f.model_type) == model_type) {
        return (reg.load)(weights, opts);
    }
    let file = weights
        .resolve("config.json")
        .map(|p| p.display().to_string())
        .unwrap_or_else(|_| format!("{}/config.json", weights.describe()));
    Err(ModelError::BadConfig(format!(
        "{file}: model_type {} is not supported by kind = \"candle\"; supported: {} \
         (other models can be served by an OpenAI-compatible server, kind = \"openai\")",
        match model_type {
            Some(t) => format!("`{t}`"),
            None => "is missing".into(),
        },
        supported_model_types().join(", ")
    )))
}

/// `np.linspace(0, n - 1, k).round()` without repeats: `k` of `n` frames spread evenly, first
/// and last included; every frame when `k >= n`.
pub fn spread_indices(n: usize, k: usize) -> Vec<usize> {
    if k == 0 || n == 0 {
        return Vec::new();
    }
    if k >= n {
        return (0..n).collect();
    }
    if k == 1 {
        return vec![n / 2];
    }
    (0..k)
        .map(|i| ((i * (n - 1)) as f64 / (k - 1) as f64).round() as usize)
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn spread_indices_cover_the_clip() {
        assert_eq!(spread_indices(10, 4), vec![0, 3, 6, 9]);
        assert_eq!(spread_indices(3, 8), vec![0, 1, 2]);
        assert_eq!(spread_indices(5, 1), vec![2]);
        assert!(spread_indices(0, 3).is_empty());
    }

    #[test]
    fn every_family_is_registered_once() {
        let mut t = supported_model_types();
        assert_eq!(
            t,
            vec![
                "qwen3_vl",
                "video_llava",
                "videollama2",
                "videollama2_mistral",
                "vlaad",
                "video_llama"
            ]
        );
        t.dedup();
        assert_eq!(t.len(), FAMILIES.len());
    }
}
