//! `config.json` of a Qwen3-VL checkpoint, read the way transformers reads it.
//!
//! Checkpoints disagree on where some fields live (transformers 4.57 wrote `rope_theta` and
//! `rope_scaling` into `text_config`; 5.x writes `rope_parameters`; the tie flag sits at the top
//! level), so parsing goes through [`Config::from_json`], which accepts every layout and fills
//! the same defaults as `Qwen3VLConfig`, instead of a bare serde derive that would reject a real
//! checkpoint for a moved key.

use candle_nn::Activation;
use serde_json::Value;

use crate::ModelError;

/// The vision tower (`vision_config`).
#[derive(Debug, Clone, PartialEq)]
pub struct VisionConfig {
    pub depth: usize,
    pub hidden_size: usize,
    /// Activation of the blocks' MLPs (`gelu_pytorch_tanh` in every released checkpoint). The
    /// patch mergers always use the exact (erf) GELU, as `nn.GELU()` does in the reference.
    pub hidden_act: Activation,
    pub intermediate_size: usize,
    pub num_heads: usize,
    pub in_channels: usize,
    pub patch_size: usize,
    pub spatial_merge_size: usize,
    pub temporal_patch_size: usize,
    pub out_hidden_size: usize,
    /// Size of the learned position table; a perfect square (its side is resampled per grid).
    pub num_position_embeddings: usize,
    /// Blocks whose output also feeds the text model's first layers (DeepStack).
    pub deepstack_visual_indexes: Vec<usize>,
    /// Base of the 2-D axial rotary embedding.
    pub rope_theta: f64,
}

impl VisionConfig {
    pub fn head_dim(&self) -> usize {
        self.hidden_size / self.num_heads
    }

    /// Values a patch row holds: channels x temporal patch x patch x patch.
    pub fn patch_dim(&self) -> usize {
        self.in_channels * self.temporal_patch_size * self.patch_size * self.patch_size
    }
}

/// The language model (`text_config`).
#[derive(Debug, Clone, PartialEq)]
pub struct TextConfig {
    pub vocab_size: usize,
    pub hidden_size: usize,
    pub intermediate_size: usize,
    pub num_hidden_layers: usize,
    pub num_attention_heads: usize,
    pub num_key_value_heads: usize,
    pub head_dim: usize,
    pub hidden_act: Activation,
    pub rms_norm_eps: f64,
    pub rope_theta: f64,
    /// How many of the `head_dim / 2` rotary frequencies follow the temporal, height and width
    /// position; they are interleaved (T H W T H W ...), the layout Qwen3-VL was trained with.
    pub mrope_section: [usize; 3],
    pub attention_bias: bool,
    pub max_position_embeddings: usize,
}

/// A whole `Qwen3VLForConditionalGeneration` config.
#[derive(Debug, Clone, PartialEq)]
pub struct Config {
    pub text: TextConfig,
    pub vision: VisionConfig,
    pub image_token_id: u32,
    pub video_token_id: u32,
    pub vision_start_token_id: u32,
    pub vision_end_token_id: u32,
    /// `lm_head` shares the token embedding (small checkpoints).
    pub tie_word_embeddings: bool,
}

fn bad(msg: impl std::fmt::Display) -> ModelError {
    ModelError::BadConfig(format!("Qwen3-VL config.json: {msg}"))
}

/// Typed reads from a JSON object with the key path in every error.
struct Obj<'a> {
    v: &'a serde_json::Map<String, Value>,
    path: &'static str,
}

impl<'a> Obj<'a> {
    fn of(v: &'a Value, path: &'static str) -> Result<Self, ModelError> {
        v.as_object()
            .map(|v| Obj { v, path })
            .ok_or_else(|| bad(format!("`{path}` is not an object")))
    }

    fn usize_or(&self, key: &str, default: Option<usize>) -> Result<usize, ModelError> {
        match self.v.get(key) {
            None | Some(Value::Null) => {
                default.ok_or_else(|| bad(format!("`{}.{key}` is missing", self.path)))
            }
            Some(x) => x
                .as_u64()
                .map(|x| x as usize)
                .ok_or_else(|| bad(format!("`{}.{key}` = {x} is not a whole number", self.path))),
        }
    }

    fn req(&self, key: &str) -> Result<usize, ModelError> {
        self.usize_or(key, None)
    }

    fn opt(&self, key: &str, default: usize) -> Result<usize, ModelError> {
        self.usize_or(key, Some(default))
    }

    fn f64_or(&self, key: &str, default: f64) -> Result<f64, ModelError> {
        match self.v.get(key) {
            None | Some(Value::Null) => Ok(default),
            Some(x) => x
                .as_f64()
                .ok_or_else(|| bad(format!("`{}.{key}` = {x} is not a number", self.path))),
        }
    }

    fn bool_or(&self, key: &str, default: bool) -> Result<bool, ModelError> {
        match self.v.get(key) {
            None | Some(Value::Null) => Ok(default),
            Some(x) => x
                .as_bool()
                .ok_or_else(|| bad(format!("`{}.{key}` = {x} is not a boolean", self.path))),
        }
    }

    fn act_or(&self, key: &str, default: &str) -> Result<Activation, ModelError> {
        let name = match self.v.get(key) {
            None | Some(Value::Null) => default.to_string(),
            Some(Value::String(s)) => s.clone(),
            Some(x) => return Err(bad(format!("`{}.{key}` = {x} is not a string", self.path))),
        };
        activation(&name).ok_or_else(|| {
            bad(format!(
                "`{}.{key}` = \"{name}\" is not an activation this engine implements \
                 (gelu, gelu_pytorch_tanh, gelu_new, silu, swish, relu)",
                self.path
            ))
        })
    }
}

/// transformers' `ACT2FN` names for the activations these models use. `gelu` is the exact
/// (erf) GELU; the tanh approximation has its own names.
pub fn activation(name: &str) -> Option<Activation> {
    Some(match name {
        "gelu" => Activation::Gelu,
        "gelu_pytorch_tanh" | "gelu_new" | "gelu_fast" => Activation::GeluPytorchTanh,
        "silu" | "swish" => Activation::Silu,
        "relu" => Activation::Relu,
        _ => return None,
    })
}

/// `rope_parameters` (5.x) or `rope_scaling` + `rope_theta` (4.x), merged.
fn rope_params(tc: &serde_json::Map<String, Value>) -> serde_json::Map<String, Value> {
    let mut out = serde_json::Map::new();
    for key in ["rope_scaling", "rope_parameters"] {
        if let Some(Value::Object(m)) = tc.get(key) {
            out.extend(m.clone());
        }
    }
    if let Some(t) = tc.get("rope_theta") {
        out.entry("rope_theta").or_insert(t.clone());
    }
    out
}

impl Config {
    /// Parses a `config.json` value.
    pub fn from_json(v: &Value) -> Result<Self, ModelError> {
        let top = Obj::of(v, "config")?;
        let tv = top
            .v
            .get("text_config")
            .ok_or_else(|| bad("`text_config` is missing"))?;
        let vv = top
            .v
            .get("vision_config")
            .ok_or_else(|| bad("`vision_config` is missing"))?;
        let t = Obj::of(tv, "text_config")?;
        let vis = Obj::of(vv, "vision_config")?;

        let rope = rope_params(t.v);
        let rope = Obj {
            v: &rope,
            path: "text_config.rope_parameters",
        };
        let rope_type = rope.v.get("rope_type").and_then(Value::as_str);
        if let Some(rt) = rope_type.filter(|rt| *rt != "default" && *rt != "mrope") {
            return Err(bad(format!(
                "rope_type \"{rt}\" is not supported (only the default M-RoPE)"
            )));
        }
        let mrope_section = match rope.v.get("mrope_section") {
            None | Some(Value::Null) => [24, 20, 20],
            Some(Value::Array(a)) if a.len() == 3 => {
                let mut s = [0usize; 3];
                for (i, x) in a.iter().enumerate() {
                    s[i] = x
                        .as_u64()
                        .ok_or_else(|| bad(format!("mrope_section entry {x} is not a number")))?
                        as usize;
                }
                s
            }
            Some(x) => return Err(bad(format!("mrope_section {x} is not three numbers"))),
        };
        if !rope.bool_or("mrope_interleaved", true)? {
            // Qwen2.5-VL's chunked layout; Qwen3-VL always interleaves.
            return Err(bad(
                "mrope_interleaved = false (the chunked Qwen2-VL layout) is not supported",
            ));
        }

        let hidden = t.req("hidden_size")?;
        let heads = t.req("num_attention_heads")?;
        let text = TextConfig {
            vocab_size: t.req("vocab_size")?,
            hidden_size: hidden,
            intermediate_size: t.req("intermediate_size")?,
            num_hidden_layers: t.req("num_hidden_layers")?,
            num_attention_heads: heads,
            num_key_value_heads: t.opt("num_key_value_heads", heads)?,
            head_dim: t.opt("head_dim", hidden / heads.max(1))?,
            hidden_act: t.act_or("hidden_act", "silu")?,
            rms_norm_eps: t.f64_or("rms_norm_eps", 1e-6)?,
            rope_theta: rope.f64_or("rope_theta", 5_000_000.0)?,
            mrope_section,
            attention_bias: t.bool_or("attention_bias", false)?,
            max_position_embeddings: t.opt("max_position_embeddings", 128_000)?,
        };

        let vrope = match vis.v.get("rope_parameters") {
            Some(Value::Object(m)) => m.clone(),
            _ => serde_json::Map::new(),
        };
        let vrope = Obj {
            v: &vrope,
            path: "vision_config.rope_parameters",
        };
        let vision = VisionConfig {
            depth: vis.opt("depth", 27)?,
            hidden_size: vis.opt("hidden_size", 1152)?,
            hidden_act: vis.act_or("hidden_act", "gelu_pytorch_tanh")?,
            intermediate_size: vis.opt("intermediate_size", 4304)?,
            num_heads: vis.opt("num_heads", 16)?,
            in_channels: vis.opt("in_channels", 3)?,
            patch_size: vis.opt("patch_size", 16)?,
            spatial_merge_size: vis.opt("spatial_merge_size", 2)?,
            temporal_patch_size: vis.opt("temporal_patch_size", 2)?,
            out_hidden_size: vis.opt("out_hidden_size", 3584)?,
            num_position_embeddings: vis.opt("num_position_embeddings", 2304)?,
            deepstack_visual_indexes: match vis.v.get("deepstack_visual_indexes") {
                None | Some(Value::Null) => vec![8, 16, 24],
                Some(Value::Array(a)) => a
                    .iter()
                    .map(|x| {
                        x.as_u64().map(|x| x as usize).ok_or_else(|| {
                            bad(format!(
                                "deepstack_visual_indexes entry {x} is not a number"
                            ))
                        })
                    })
                    .collect::<Result<_, _>>()?,
                Some(x) => return Err(bad(format!("deepstack_visual_indexes {x} is not a list"))),
            },
            rope_theta: vrope.f64_or("rope_theta", 10_000.0)?,
        };

        let cfg = Config {
            text,
            vision,
            image_token_id: top.opt("image_token_id", 151_655)? as u32,
            video_token_id: top.opt("video_token_id", 151_656)? as u32,
            vision_start_token_id: top.opt("vision_start_token_id", 151_652)? as u32,
            vision_end_token_id: top.opt("vision_end_token_id", 151_653)? as u32,
            tie_word_embeddings: match top.v.get("tie_word_embeddings") {
                Some(Value::Bool(b)) => *b,
                _ => t.bool_or("tie_word_embeddings", false)?,
            },
        };
        cfg.validate()?;
        Ok(cfg)
    }

    /// Shape rules the forward pass relies on, checked once at load so a bad checkpoint fails
    /// with a sentence instead of a shape error deep in a matmul on the first clip.
    pub fn validate(&self) -> Result<(), ModelError> {
        let (t, v) = (&self.text, &self.vision);
        let positive = [
            ("text_config.hidden_size", t.hidden_size),
            ("text_config.num_attention_heads", t.num_attention_heads),
            ("text_config.num_key_value_heads", t.num_key_value_heads),
            ("text_config.head_dim", t.head_dim),
            ("text_config.vocab_size", t.vocab_size),
            ("vision_config.hidden_size", v.hidden_size),
            ("vision_config.num_heads", v.num_heads),
            ("vision_config.patch_size", v.patch_size),
            ("vision_config.spatial_merge_size", v.spatial_merge_size),
            ("vision_config.temporal_patch_size", v.temporal_patch_size),
            (
                "vision_config.num_position_embeddings",
                v.num_position_embeddings,
            ),
        ];
        for (name, x) in positive {
            if x == 0 {
                return Err(bad(format!("`{name}` must be positive")));
            }
        }
        if t.num_attention_heads % t.num_key_value_heads != 0 {
            return Err(bad(format!(
                "{} attention heads are not a multiple of {} key/value heads",
                t.num_attention_heads, t.num_key_value_heads
            )));
        }
        // Sections need not add up to head_dim / 2: the reference lets height and width take
        // their interleaved slots up to 3 x section and leaves every other frequency temporal.
        if t.head_dim % 2 != 0 {
            return Err(bad(format!("head_dim {} must be even", t.head_dim)));
        }
        if v.hidden_size % v.num_heads != 0 || v.head_dim() % 4 != 0 {
            return Err(bad(format!(
                "vision head size {}/{} must be a whole multiple of 4 (2-D rotary embedding)",
                v.hidden_size, v.num_heads
            )));
        }
        let side = (v.num_position_embeddings as f64).sqrt().round() as usize;
        if side * side != v.num_position_embeddings {
            return Err(bad(format!(
                "vision_config.num_position_embeddings = {} is not a perfect square",
                v.num_position_embeddings
            )));
        }
        if let Some(&i) = v.deepstack_visual_indexes.iter().find(|&&i| i >= v.depth) {
            return Err(bad(format!(
                "deepstack index {i} is past the vision depth {}",
                v.depth
            )));
        }
        if v.deepstack_visual_indexes.len() > t.num_hidden_layers {
            return Err(bad(format!(
                "{} deepstack features but only {} text layers take them",
                v.deepstack_visual_indexes.len(),
                t.num_hidden_layers
            )));
        }
        Ok(())
    }

    /// Side of the square learned position table of the vision tower.
    pub fn num_grid_per_side(&self) -> usize {
        (self.vision.num_position_embeddings as f64).sqrt().round() as usize
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn minimal() -> Value {
        serde_json::json!({
            "text_config": {
                "vocab_size": 10, "hidden_size": 16, "intermediate_size": 32,
                "num_hidden_layers": 1, "num_attention_heads": 2, "num_key_value_heads": 1,
                "head_dim": 8, "rope_parameters": {"rope_theta": 1000.0,
                "mrope_section": [2, 1, 1], "mrope_interleaved": true, "rope_type": "default"}
            },
            "vision_config": {"depth": 1, "hidden_size": 16, "num_heads": 2,
                "num_position_embeddings": 16, "deepstack_visual_indexes": [0],
                "out_hidden_size": 16}
        })
    }

    #[test]
    fn reads_both_rope_layouts() {
        let c = Config::from_json(&minimal()).unwrap();
        assert_eq!(c.text.rope_theta, 1000.0);
        assert_eq!(c.text.mrope_section, [2, 1, 1]);
        assert_eq!(c.vision.rope_theta, 10_000.0);
        assert_eq!(c.vision.hidden_act, Activation::GeluPytorchTanh);

        let mut v = minimal();
        let tc = v["text_config"].as_object_mut().unwrap();
        tc.remove("rope_parameters");
        tc.insert("rope_theta".into(), serde_json::json!(5e6));
        tc.insert(
            "rope_scaling".into(),
            serde_json::json!({"mrope_section": [1, 2, 1], "rope_type": "default"}),
        );
        let c = Config::from_json(&v).unwrap();
        assert_eq!(c.text.rope_theta, 5e6);
        assert_eq!(c.text.mrope_section, [1, 2, 1]);
    }

    #[test]
    fn rejects_what_it_cannot_run_with_the_key_named() {
        let mut v = minimal();
        v["text_config"]["rope_parameters"]["mrope_section"] = serde_json::json!([3, 1]);
        let e = Config::from_json(&v).unwrap_err().to_string();
        assert!(e.contains("mrope_section"), "{e}");
        let mut v = minimal();
        v["text_config"]["head_dim"] = serde_json::json!(7);
        let e = Config::from_json(&v).unwrap_err().to_string();
        assert!(e.contains("even"), "{e}");

        let mut v = minimal();
        v["vision_config"]["num_position_embeddings"] = serde_json::json!(15);
        let e = Config::from_json(&v).unwrap_err().to_string();
        assert!(e.contains("perfect square"), "{e}");

        let mut v = minimal();
        v["text_config"]["hidden_act"] = serde_json::json!("mystery");
        let e = Config::from_json(&v).unwrap_err().to_string();
        assert!(e.contains("text_config.hidden_act"), "{e}");

        let mut v = minimal();
        v["text_config"]
            .as_object_mut()
            .unwrap()
            .remove("vocab_size");
        let e = Config::from_json(&v).unwrap_err().to_string();
        assert!(e.contains("text_config.vocab_size"), "{e}");

        assert!(Config::from_json(&serde_json::json!({})).is_err());
    }

    #[test]
    fn activations_follow_act2fn() {
        assert_eq!(activation("gelu"), Some(Activation::Gelu));
        assert_eq!(
            activation("gelu_pytorch_tanh"),
            Some(Activation::GeluPytorchTanh)
        );
        assert_eq!(activation("silu"), Some(Activation::Silu));
        assert_eq!(activation("quick_gelu"), None);
    }
}
