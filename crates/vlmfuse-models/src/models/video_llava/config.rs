//! `config.json` of a `video_llava` checkpoint, read with transformers 5.23's defaults: the
//! published `LanguageBind/Video-LLaVA-7B-hf` config leaves most LLaMA fields out (they mean
//! `LlamaConfig`'s defaults) and gives the CLIP towers only a few fields (the rest are
//! `VideoLlavaConfig`'s vision defaults, then `CLIPVisionConfig`'s). A field we would silently
//! misread is an error here instead.

use serde::Deserialize;

use crate::ModelError;

/// An activation named the way transformers' `ACT2FN` names it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Act {
    /// `x * sigmoid(1.702 x)` (OpenAI CLIP).
    QuickGelu,
    /// Exact (erf) GELU: transformers' `"gelu"`.
    GeluErf,
    /// The tanh approximation: `"gelu_new"`, `"gelu_pytorch_tanh"`, `"gelu_fast"`.
    GeluTanh,
    Silu,
    Relu,
}

impl Act {
    pub fn from_hf(name: &str) -> Result<Self, ModelError> {
        Ok(match name {
            "quick_gelu" => Act::QuickGelu,
            "gelu" => Act::GeluErf,
            "gelu_new" | "gelu_pytorch_tanh" | "gelu_fast" => Act::GeluTanh,
            "silu" | "swish" => Act::Silu,
            "relu" => Act::Relu,
            other => {
                return Err(ModelError::BadConfig(format!(
                    "activation `{other}` is not supported (quick_gelu, gelu, gelu_new, \
                     gelu_pytorch_tanh, silu, relu)"
                )))
            }
        })
    }

    pub fn apply(&self, xs: &candle_core::Tensor) -> candle_core::Result<candle_core::Tensor> {
        match self {
            Act::QuickGelu => xs * candle_nn::ops::sigmoid(&(xs * 1.702f64)?)?,
            Act::GeluErf => xs.gelu_erf(),
            Act::GeluTanh => xs.gelu(),
            Act::Silu => xs.silu(),
            Act::Relu => xs.relu(),
        }
    }
}

/// The CLIP vision tower of each frame (`CLIPVisionConfig`).
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(default)]
pub struct VisionConfig {
    pub hidden_size: usize,
    pub intermediate_size: usize,
    pub num_hidden_layers: usize,
    pub num_attention_heads: usize,
    pub num_channels: usize,
    pub image_size: usize,
    pub patch_size: usize,
    pub hidden_act: String,
    pub layer_norm_eps: f64,
}

impl Default for VisionConfig {
    /// `VideoLlavaConfig`'s vision defaults (ViT-L/14 at 224) over `CLIPVisionConfig`'s.
    fn default() -> Self {
        Self {
            hidden_size: 1024,
            intermediate_size: 4096,
            num_hidden_layers: 24,
            num_attention_heads: 16,
            num_channels: 3,
            image_size: 224,
            patch_size: 14,
            hidden_act: "quick_gelu".into(),
            layer_norm_eps: 1e-5,
        }
    }
}

impl VisionConfig {
    /// Patches per side.
    pub fn grid(&self) -> usize {
        self.image_size / self.patch_size
    }

    /// Tokens per frame including CLS: `(image_size / patch_size)² + 1`.
    pub fn tokens_per_frame(&self) -> usize {
        self.grid() * self.grid() + 1
    }

    pub fn head_dim(&self) -> usize {
        self.hidden_size / self.num_attention_heads
    }

    pub(crate) fn check(&self) -> Result<(), ModelError> {
        Act::from_hf(&self.hidden_act)?;
        if self.patch_size == 0 || !self.image_size.is_multiple_of(self.patch_size) {
            return Err(ModelError::BadConfig(format!(
                "vision_config: image_size {} is not a multiple of patch_size {}",
                self.image_size, self.patch_size
            )));
        }
        if self.num_attention_heads == 0
            || !self.hidden_size.is_multiple_of(self.num_attention_heads)
        {
            return Err(ModelError::BadConfig(format!(
                "vision_config: hidden_size {} not divisible by num_attention_heads {}",
                self.hidden_size, self.num_attention_heads
            )));
        }
        if self.num_channels != 3 {
            return Err(ModelError::BadConfig(format!(
                "vision_config: num_channels {} (frames are RGB)",
                self.num_channels
            )));
        }
        if self.num_hidden_layers == 0 {
            return Err(ModelError::BadConfig(
                "vision_config: num_hidden_layers is 0".into(),
            ));
        }
        Ok(())
    }
}

/// How positions turn into rotary frequencies.
#[derive(Debug, Clone, PartialEq)]
pub enum RopeScaling {
    None,
    /// Positions divided by `factor` (`rope_type = "linear"`).
    Linear {
        factor: f64,
    },
    /// Llama 3.1's frequency-dependent scaling.
    Llama3 {
        factor: f64,
        low_freq_factor: f64,
        high_freq_factor: f64,
        original_max_position_embeddings: f64,
    },
}

/// The LLaMA language model (`LlamaConfig`).
#[derive(Debug, Clone, PartialEq)]
pub struct TextConfig {
    pub vocab_size: usize,
    pub hidden_size: usize,
    pub intermediate_size: usize,
    pub num_hidden_layers: usize,
    pub num_attention_heads: usize,
    pub num_key_value_heads: usize,
    pub head_dim: usize,
    pub hidden_act: String,
    pub max_position_embeddings: usize,
    pub rms_norm_eps: f64,
    pub rope_theta: f64,
    pub rope_scaling: RopeScaling,
    pub attention_bias: bool,
    pub mlp_bias: bool,
}

impl TextConfig {
    /// A LLaMA-style language model's config (`LlamaConfig`, or `MistralConfig` read with
    /// [`TextConfig::mistral_json`]), checked; `types` are the `model_type`s accepted.
    fn from_raw(raw: &RawText, types: &[&str]) -> Result<Self, ModelError> {
        if !types.contains(&raw.model_type.as_str()) {
            return Err(ModelError::BadConfig(format!(
                "text_config.model_type `{}`: only {} language models are supported",
                raw.model_type,
                types.join(", ")
            )));
        }
        if raw.pretraining_tp.unwrap_or(1) != 1 {
            // transformers ignores it at inference too, but say so rather than surprise.
            tracing::debug!(
                tp = raw.pretraining_tp,
                "pretraining_tp ignored (no effect on outputs)"
            );
        }
        if raw.num_attention_heads == 0 {
            return Err(ModelError::BadConfig(
                "text_config: num_attention_heads is 0".into(),
            ));
        }
        let kv = raw.num_key_value_heads.unwrap_or(raw.num_attention_heads);
        if kv == 0 || !raw.num_attention_heads.is_multiple_of(kv) {
            return Err(ModelError::BadConfig(format!(
                "text_config: {} attention heads are not a multiple of {kv} key/value heads",
                raw.num_attention_heads
            )));
        }
        let head_dim = raw
            .head_dim
            .unwrap_or(raw.hidden_size / raw.num_attention_heads);
        if head_dim == 0 || !head_dim.is_multiple_of(2) {
            return Err(ModelError::BadConfig(format!(
                "text_config: head_dim {head_dim} must be even for rotary embeddings"
            )));
        }
        Act::from_hf(&raw.hidden_act)?;
        let (rope_theta, rope_scaling) = rope_from(raw)?;
        Ok(TextConfig {
            vocab_size: raw.vocab_size,
            hidden_size: raw.hidden_size,
            intermediate_size: raw.intermediate_size,
            num_hidden_layers: raw.num_hidden_layers,
            num_attention_heads: raw.num_attention_heads,
            num_key_value_heads: kv,
            head_dim,
            hidden_act: raw.hidden_act.clone(),
            max_position_embeddings: raw.max_position_embeddings,
            rms_norm_eps: raw.rms_norm_eps,
            rope_theta,
            rope_scaling,
            attention_bias: raw.attention_bias,
            mlp_bias: raw.mlp_bias,
        })
    }

    /// A LLaMA config at the top level of a checkpoint's `config.json` (`LlamaConfig`'s
    /// defaults), as a LLaMA directory has it.
    pub fn llama_json(v: &serde_json::Value) -> Result<Self, ModelError> {
        let raw: RawText = serde_json::from_value(v.clone())
            .map_err(|e| ModelError::BadConfig(format!("LLaMA config.json: {e}")))?;
        Self::from_raw(&raw, &["llama"])
    }

    /// A Mistral config at the top level of `config.json` (VideoLLaMA2's LLM, whose
    /// `model_type` is the checkpoint's own), with `MistralConfig`'s defaults, and its
    /// `sliding_window` (`None`: full attention).
    pub fn mistral_json(v: &serde_json::Value) -> Result<(Self, Option<usize>), ModelError> {
        let mut raw: RawText = serde_json::from_value(v.clone())
            .map_err(|e| ModelError::BadConfig(format!("config.json: {e}")))?;
        let given = |k: &str| v.get(k).is_some_and(|x| !x.is_null());
        // MistralConfig's defaults where LlamaConfig's differ.
        if !given("intermediate_size") {
            raw.intermediate_size = 14336;
        }
        if !given("num_key_value_heads") {
            raw.num_key_value_heads = Some(8);
        }
        if !given("max_position_embeddings") {
            raw.max_position_embeddings = 4096 * 32;
        }
        if !given("rms_norm_eps") {
            raw.rms_norm_eps = 1e-6;
        }
        raw.model_type = "mistral".into();
        let window = match v.get("sliding_window") {
            None => Some(4096),
            Some(serde_json::Value::Null) => None,
            Some(x) => Some(x.as_u64().ok_or_else(|| {
                ModelError::BadConfig("config.json: sliding_window is not an integer".into())
            })? as usize),
        };
        Ok((Self::from_raw(&raw, &["mistral"])?, window))
    }
}

/// Raw `text_config` with `LlamaConfig`'s defaults; normalised into [`TextConfig`].
#[derive(Debug, Clone, Deserialize)]
#[serde(default)]
struct RawText {
    model_type: String,
    vocab_size: usize,
    hidden_size: usize,
    intermediate_size: usize,
    num_hidden_layers: usize,
    num_attention_heads: usize,
    num_key_value_heads: Option<usize>,
    head_dim: Option<usize>,
    hidden_act: String,
    max_position_embeddings: usize,
    rms_norm_eps: f64,
    rope_theta: Option<f64>,
    rope_scaling: Option<serde_json::Value>,
    rope_parameters: Option<serde_json::Value>,
    attention_bias: bool,
    mlp_bias: bool,
    pretraining_tp: Option<usize>,
    tie_word_embeddings: Option<bool>,
    pad_token_id: Option<i64>,
}

impl Default for RawText {
    fn default() -> Self {
        Self {
            model_type: "llama".into(),
            vocab_size: 32000,
            hidden_size: 4096,
            intermediate_size: 11008,
            num_hidden_layers: 32,
            num_attention_heads: 32,
            num_key_value_heads: None,
            head_dim: None,
            hidden_act: "silu".into(),
            max_position_embeddings: 2048,
            rms_norm_eps: 1e-6,
            rope_theta: None,
            rope_scaling: None,
            rope_parameters: None,
            attention_bias: false,
            mlp_bias: false,
            pretraining_tp: None,
            tie_word_embeddings: None,
            pad_token_id: None,
        }
    }
}

fn rope_from(raw: &RawText) -> Result<(f64, RopeScaling), ModelError> {
    // transformers 5 writes `rope_parameters` (theta inside); older configs `rope_theta` plus an
    // optional `rope_scaling`. Both mean the same thing.
    let params = raw.rope_parameters.as_ref().or(raw.rope_scaling.as_ref());
    let theta = raw
        .rope_parameters
        .as_ref()
        .and_then(|p| p.get("rope_theta"))
        .and_then(|t| t.as_f64())
        .or(raw.rope_theta)
        .unwrap_or(10_000.0);
    let Some(p) = params.filter(|p| !p.is_null()) else {
        return Ok((theta, RopeScaling::None));
    };
    let kind = p
        .get("rope_type")
        .or_else(|| p.get("type"))
        .and_then(|t| t.as_str())
        .unwrap_or("default");
    let num = |k: &str| -> Result<f64, ModelError> {
        p.get(k)
            .and_then(|v| v.as_f64())
            .ok_or_else(|| ModelError::BadConfig(format!("text_config: rope `{kind}` needs `{k}`")))
    };
    let scaling = match kind {
        "default" => RopeScaling::None,
        "linear" => RopeScaling::Linear {
            factor: num("factor")?,
        },
        "llama3" => RopeScaling::Llama3 {
            factor: num("factor")?,
            low_freq_factor: num("low_freq_factor")?,
            high_freq_factor: num("high_freq_factor")?,
            original_max_position_embeddings: num("original_max_position_embeddings")?,
        },
        other => {
            return Err(ModelError::BadConfig(format!(
                "text_config: rope_type `{other}` is not supported (default, linear, llama3)"
            )))
        }
    };
    Ok((theta, scaling))
}

/// Which hidden states of the vision tower feed the projector.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum FeatureLayers {
    One(i64),
    Many(Vec<i64>),
}

impl FeatureLayers {
    pub fn as_slice(&self) -> &[i64] {
        match self {
            FeatureLayers::One(l) => std::slice::from_ref(l),
            FeatureLayers::Many(v) => v,
        }
    }

    /// Indices into transformers' `hidden_states` tuple (`[embeddings, layer 1, …, layer L]`,
    /// so `L + 1` entries; negative counts from the end). `-2` is the output of layer `L - 1`.
    pub fn resolve(&self, num_layers: usize) -> Result<Vec<usize>, ModelError> {
        let n = num_layers as i64 + 1;
        self.as_slice()
            .iter()
            .map(|&l| {
                let i = if l < 0 { n + l } else { l };
                if (0..n).contains(&i) {
                    Ok(i as usize)
                } else {
                    Err(ModelError::BadConfig(format!(
                        "vision_feature_layer {l} is outside the {n} hidden states of a \
                         {num_layers}-layer tower"
                    )))
                }
            })
            .collect()
    }
}

/// What the `vision_feature_select_strategy` does to image features (videos keep every token
/// in transformers' `get_video_features`, whatever the strategy).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SelectStrategy {
    /// Drop the CLS token.
    Default,
    /// Keep it.
    Full,
}

/// The whole `config.json`.
#[derive(Debug, Clone, PartialEq)]
pub struct VideoLlavaConfig {
    pub vision: VisionConfig,
    pub text: TextConfig,
    pub image_token_id: u32,
    pub video_token_id: u32,
    pub pad_token_id: Option<u32>,
    pub projector_act: Act,
    pub projector_bias: bool,
    pub feature_layers: FeatureLayers,
    pub select_strategy: SelectStrategy,
    pub tie_word_embeddings: bool,
}

fn field<'a>(v: &'a serde_json::Value, k: &str) -> Option<&'a serde_json::Value> {
    v.get(k).filter(|x| !x.is_null())
}

impl VideoLlavaConfig {
    /// Parses `config.json`, refusing other architectures by name so a wrong directory fails
    /// with a message that says so.
    pub fn from_json(v: &serde_json::Value) -> Result<Self, ModelError> {
        let mt = v.get("model_type").and_then(|m| m.as_str()).unwrap_or("");
        if mt != "video_llava" {
            return Err(ModelError::BadConfig(format!(
                "config.json has model_type `{mt}`, not `video_llava`"
            )));
        }
        let vision: VisionConfig = match field(v, "vision_config") {
            Some(vc) => serde_json::from_value(vc.clone())
                .map_err(|e| ModelError::BadConfig(format!("vision_config: {e}")))?,
            None => VisionConfig::default(),
        };
        vision.check()?;
        let raw: RawText = match field(v, "text_config") {
            Some(tc) => serde_json::from_value(tc.clone())
                .map_err(|e| ModelError::BadConfig(format!("text_config: {e}")))?,
            None => RawText::default(),
        };
        let text = TextConfig::from_raw(&raw, &["llama"])?;

        let id = |k: &str, alias: &str, default: u32| -> Result<u32, ModelError> {
            match field(v, k).or_else(|| field(v, alias)) {
                None => Ok(default),
                Some(x) => x.as_u64().map(|x| x as u32).ok_or_else(|| {
                    ModelError::BadConfig(format!("config.json: `{k}` is not a token id"))
                }),
            }
        };
        let image_token_id = id("image_token_index", "image_token_id", 32000)?;
        let video_token_id = id("video_token_index", "video_token_id", 32001)?;
        let pad_token_id = field(v, "pad_token_id")
            .and_then(|x| x.as_u64())
            .map(|x| x as u32)
            .or(raw.pad_token_id.and_then(|p| u32::try_from(p).ok()));

        let projector_act = Act::from_hf(
            field(v, "projector_hidden_act")
                .and_then(|x| x.as_str())
                .unwrap_or("gelu"),
        )?;
        let projector_bias = field(v, "multimodal_projector_bias")
            .and_then(|x| x.as_bool())
            .unwrap_or(true);
        let feature_layers = match field(v, "vision_feature_layer") {
            None => FeatureLayers::One(-2),
            Some(serde_json::Value::Number(n)) => {
                FeatureLayers::One(n.as_i64().ok_or_else(|| {
                    ModelError::BadConfig("vision_feature_layer is not an integer".into())
                })?)
            }
            Some(serde_json::Value::Array(a)) if !a.is_empty() => FeatureLayers::Many(
                a.iter()
                    .map(|x| {
                        x.as_i64().ok_or_else(|| {
                            ModelError::BadConfig(
                                "vision_feature_layer list holds a non-integer".into(),
                            )
                        })
                    })
                    .collect::<Result<_, _>>()?,
            ),
            Some(other) => {
                return Err(ModelError::BadConfig(format!(
                    "vision_feature_layer {other} is neither an integer nor a non-empty list"
                )))
            }
        };
        feature_layers.resolve(vision.num_hidden_layers)?;
        let select_strategy = match field(v, "vision_feature_select_strategy")
            .and_then(|x| x.as_str())
            .unwrap_or("default")
        {
            "default" => SelectStrategy::Default,
            "full" => SelectStrategy::Full,
            other => {
                return Err(ModelError::BadConfig(format!(
                    "vision_feature_select_strategy `{other}` (expected default or full)"
                )))
            }
        };
        // The composite model's flag governs tying in transformers (default false); the text
        // config's is the fallback for exports that only set it there.
        let tie_word_embeddings = field(v, "tie_word_embeddings")
            .and_then(|x| x.as_bool())
            .or(raw.tie_word_embeddings)
            .unwrap_or(false);
        for (name, tid) in [("image", image_token_id), ("video", video_token_id)] {
            if tid as usize >= text.vocab_size {
                return Err(ModelError::BadConfig(format!(
                    "{name} token id {tid} is outside the vocabulary ({})",
                    text.vocab_size
                )));
            }
        }
        Ok(Self {
            vision,
            text,
            image_token_id,
            video_token_id,
            pad_token_id,
            projector_act,
            projector_bias,
            feature_layers,
            select_strategy,
            tie_word_embeddings,
        })
    }

    /// Input width of the projector: the tower's hidden size times the number of feature layers.
    pub fn projector_in(&self) -> usize {
        self.vision.hidden_size * self.feature_layers.as_slice().len()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn published_7b_config_reads_with_transformers_defaults() {
        // The fields LanguageBind/Video-LLaVA-7B-hf spells out; everything else is a default.
        let v = serde_json::json!({
            "architectures": ["VideoLlavaForConditionalGeneration"],
            "ignore_index": -100, "image_token_index": 32000, "model_type": "video_llava",
            "pad_token_id": 32001, "projector_hidden_act": "gelu",
            "text_config": {"_name_or_path": "lmsys/vicuna-7b-v1.5",
                "architectures": ["LlamaForCausalLM"], "max_position_embeddings": 4096,
                "model_type": "llama", "pad_token_id": 0, "rms_norm_eps": 1e-05,
                "torch_dtype": "float16", "vocab_size": 32064},
            "video_token_index": 32001,
            "vision_config": {"hidden_size": 1024, "image_size": 224, "intermediate_size": 4096,
                "model_type": "clip_vision_model", "num_attention_heads": 16,
                "num_hidden_layers": 24, "patch_size": 14, "projection_dim": 768,
                "vocab_size": 32000},
            "vision_feature_layer": -2, "vision_feature_select_strategy": "default"
        });
        let c = VideoLlavaConfig::from_json(&v).unwrap();
        assert_eq!(c.text.hidden_size, 4096);
        assert_eq!(c.text.num_hidden_layers, 32);
        assert_eq!(c.text.num_key_value_heads, 32);
        assert_eq!(c.text.head_dim, 128);
        assert_eq!(c.text.intermediate_size, 11008);
        assert_eq!(c.text.rope_theta, 10_000.0);
        assert_eq!(c.text.rms_norm_eps, 1e-5);
        assert_eq!(c.vision.tokens_per_frame(), 257);
        assert_eq!(c.feature_layers.resolve(24).unwrap(), vec![23]);
        assert_eq!(c.projector_act, Act::GeluErf);
        assert!(c.projector_bias && !c.tie_word_embeddings);
        assert_eq!((c.image_token_id, c.video_token_id), (32000, 32001));
        assert_eq!(c.pad_token_id, Some(32001));
        assert_eq!(c.projector_in(), 1024);
    }

    #[test]
    fn rope_forms_and_refusals() {
        let base = |mut text: serde_json::Value| {
            text["vocab_size"] = 32064.into();
            serde_json::json!({"model_type": "video_llava", "text_config": text,
                "vision_config": {"num_hidden_layers": 2}})
        };
        let c = VideoLlavaConfig::from_json(&base(serde_json::json!({
            "rope_parameters": {"rope_type": "default", "rope_theta": 500000.0}})))
        .unwrap();
        assert_eq!(c.text.rope_theta, 500000.0);
        let c = VideoLlavaConfig::from_json(&base(serde_json::json!({
            "rope_theta": 1000.0, "rope_scaling": {"type": "linear", "factor": 2.0}})))
        .unwrap();
        assert_eq!(c.text.rope_scaling, RopeScaling::Linear { factor: 2.0 });
        assert_eq!(c.text.rope_theta, 1000.0);
        let e = VideoLlavaConfig::from_json(&base(serde_json::json!({
            "rope_scaling": {"rope_type": "yarn", "factor": 2.0}})))
        .unwrap_err();
        assert!(e.to_string().contains("yarn"), "{e}");
        let e = VideoLlavaConfig::from_json(&base(serde_json::json!({"model_type": "mistral"})))
            .unwrap_err();
        assert!(e.to_string().contains("mistral"), "{e}");
        let e = VideoLlavaConfig::from_json(&serde_json::json!({"model_type": "qwen3_vl"}))
            .unwrap_err();
        assert!(e.to_string().contains("qwen3_vl"), "{e}");
    }

    #[test]
    fn feature_layers_resolve_like_hidden_states() {
        assert_eq!(FeatureLayers::One(-2).resolve(3).unwrap(), vec![2]);
        assert_eq!(FeatureLayers::One(-1).resolve(3).unwrap(), vec![3]);
        assert_eq!(FeatureLayers::One(0).resolve(3).unwrap(), vec![0]);
        assert_eq!(
            FeatureLayers::Many(vec![-3, -1]).resolve(3).unwrap(),
            vec![1, 3]
        );
        assert!(FeatureLayers::One(-5).resolve(3).is_err());
        assert!(FeatureLayers::One(4).resolve(3).is_err());
    }

    #[test]
    fn bad_fields_are_named() {
        let v = serde_json::json!({"model_type": "video_llava",
            "text_config": {"vocab_size": 32064},
            "vision_config": {"hidden_act": "swiglu_nope"}});
        assert!(VideoLlavaConfig::from_json(&v)
            .unwrap_err()
            .to_string()
            .contains("swiglu_nope"));
        let v = serde_json::json!({"model_type": "video_llava",
            "text_config": {"vocab_size": 32064},
            "vision_feature_select_strategy": "cls"});
        assert!(VideoLlavaConfig::from_json(&v)
            .unwrap_err()
            .to_string()
            .contains("cls"));
        let v = serde_json::json!({"model_type": "video_llava",
            "text_config": {"vocab_size": 100}});
        assert!(VideoLlavaConfig::from_json(&v)
            .unwrap_err()
            .to_string()
            .contains("outside the vocabulary"));
    }
}
