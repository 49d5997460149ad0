//! PEFT LoRA adapters merged into base weights at load time, so a fine-tuned reporter runs at
//! the base model's speed with no adapter code in the forward pass: W = W0 + s·B·A, where
//! s = alpha/r (or alpha/√r with rsLoRA).

use std::collections::HashMap;

use candle_core::{DType, Tensor};
use serde::Deserialize;

use crate::weights::WeightSource;
use crate::ModelError;

/// The fields of PEFT's `adapter_config.json` that change the merged weights.
#[derive(Debug, Clone, PartialEq, Deserialize)]
pub struct LoraConfig {
    pub r: usize,
    pub lora_alpha: f64,
    #[serde(default)]
    pub use_rslora: bool,
    /// GPT-2 style `Conv1D` layers store W transposed (`[in, out]`).
    #[serde(default)]
    pub fan_in_fan_out: bool,
    #[serde(default)]
    pub use_dora: bool,
    /// Per-module overrides, keyed by a module-name suffix as PEFT matches them.
    #[serde(default)]
    pub alpha_pattern: HashMap<String, f64>,
    #[serde(default)]
    pub rank_pattern: HashMap<String, usize>,
}

impl LoraConfig {
    /// Scale for `module`, with PEFT's pattern overrides (exact name or `.`-suffix match; the
    /// rank comes from the tensor when a pattern does not give one).
    pub fn scale_for(&self, module: &str, rank_from_tensor: usize) -> f64 {
        let matches = |k: &String| module == k || module.ends_with(&format!(".{k}"));
        let alpha = self
            .alpha_pattern
            .iter()
            .find(|(k, _)| matches(k))
            .map(|(_, v)| *v)
            .unwrap_or(self.lora_alpha);
        let r = self
            .rank_pattern
            .iter()
            .find(|(k, _)| matches(k))
            .map(|(_, v)| *v)
            .unwrap_or(rank_from_tensor);
        lora_scale(alpha, r, self.use_rslora)
    }
}

/// `alpha / r`, or `alpha / sqrt(r)` for rsLoRA.
pub fn lora_scale(alpha: f64, r: usize, rslora: bool) -> f64 {
    if rslora {
        alpha / (r as f64).sqrt()
    } else {
        alpha / r as f64
    }
}

/// `W0 + scale · B·A` with `W0: [out, in]`, `A: [r, in]`, `B: [out, r]` (or `W0: [in, out]` and
/// the delta transposed when `fan_in_fan_out`). Computed in f32 and cast back to W0's dtype, so
/// a bf16 base does not lose the (small) delta to rounding twice.
pub fn merge_lora(
    w0: &Tensor,
    a: &Tensor,
    b: &Tensor,
    scale: f64,
    fan_in_fan_out: bool,
) -> Result<Tensor, ModelError> {
    let (wd, ad, bd) = (w0.dims(), a.dims(), b.dims());
    let bad = || {
        ModelError::BadWeights {
            path: Default::default(),
            reason: format!(
                "LoRA shapes do not fit: W0 {wd:?}, A {ad:?}, B {bd:?} (fan_in_fan_out {fan_in_fan_out})"
            ),
        }
    };
    if wd.len() != 2 || ad.len() != 2 || bd.len() != 2 || ad[0] != bd[1] {
        return Err(bad());
    }
    let (out, inp) = if fan_in_fan_out {
        (wd[1], wd[0])
    } else {
        (wd[0], wd[1])
    };
    if bd[0] != out || ad[1] != inp {
        return Err(bad());
    }
    let dev = w0.device();
    let a32 = a.to_device(dev)?.to_dtype(DType::F32)?;
    let b32 = b.to_device(dev)?.to_dtype(DType::F32)?;
    let mut delta = (b32.matmul(&a32)? * scale)?;
    if fan_in_fan_out {
        delta = delta.t()?.contiguous()?;
    }
    Ok((w0.to_dtype(DType::F32)? + delta)?.to_dtype(w0.dtype())?)
}

/// Merges every `lora_A`/`lora_B` pair of a PEFT adapter into `base` (in place) and returns the
/// merged base keys. Adapter keys look like `base_model.model.<module>.lora_A.weight`; the base
/// key is `<module>.weight`. Anything the merge cannot represent (DoRA, orphan halves, a module
/// missing from the base) is an error rather than a silently partial fine-tune.
pub fn merge_adapter(
    base: &mut HashMap<String, Tensor>,
    adapter: &HashMap<String, Tensor>,
    cfg: &LoraConfig,
) -> Result<Vec<String>, ModelError> {
    merge_adapter_mapped(base, adapter, cfg, |m| m.to_string())
}

/// [`merge_adapter`] for checkpoints whose module names moved between library versions: `map`
/// turns an adapter module path (after `base_model.model.`) into the base key prefix, so an
/// adapter trained against either layout (e.g. transformers 4's `language_model.model.layers`
/// and 5's `model.language_model.layers`) lands on the same weight. Pattern overrides
/// (`alpha_pattern`, `rank_pattern`) still match the adapter's own module names, as PEFT does.
pub fn merge_adapter_mapped(
    base: &mut HashMap<String, Tensor>,
    adapter: &HashMap<String, Tensor>,
    cfg: &LoraConfig,
    map: impl Fn(&str) -> String,
) -> Result<Vec<String>, ModelError> {
    if cfg.use_dora {
        return Err(ModelError::BadConfig(
            "DoRA adapters (use_dora) cannot be merged here".into(),
        ));
    }
    let mut merged = Vec::new();
    let mut modules: Vec<&str> = adapter
        .keys()
        .filter_map(|k| k.strip_suffix(".lora_A.weight"))
        .collect();
    modules.sort();
    for m in modules {
        let a = &adapter[&format!("{m}.lora_A.weight")];
        let b =
            adapter
                .get(&format!("{m}.lora_B.weight"))
                .ok_or_else(|| ModelError::BadWeights {
                    path: Default::default(),
                    reason: format!("adapter has {m}.lora_A but no lora_B"),
                })?;
        let module = m.strip_prefix("base_model.model.").unwrap_or(m);
        let key = format!("{}.weight", map(module));
        let w0 = base.get(&key).ok_or_else(|| ModelError::BadWeights {
            path: Default::default(),
            reason: format!("adapter targets `{key}`, which the base model does not have"),
        })?;
        let scale = cfg.scale_for(module, a.dims().first().copied().unwrap_or(1));
        let w = merge_lora(w0, a, b, scale, cfg.fan_in_fan_out)?;
        base.insert(key.clone(), w);
        merged.push(key);
    }
    let leftovers: Vec<&String> = adapter
        .keys()
        .filter(|k| !(k.ends_with(".lora_A.weight") || k.ends_with(".lora_B.weight")))
        .collect();
    if !leftovers.is_empty() {
        return Err(ModelError::BadWeights {
            path: Default::default(),
            reason: format!(
                "adapter tensors that are not plain LoRA A/B pairs (embedding LoRA, \
                 modules_to_save, DoRA?): {leftovers:?}"
            ),
        });
    }
    Ok(merged)
}

/// Reads `adapter_config.json` + `adapter_model.safetensors` (or `adapter_model.bin`, what
/// older PEFT releases write by default, as the VideoLLaMA2 repository's fine-tuning pins)
/// on CPU: they are merged once and dropped.
pub fn load_adapter(
    source: &WeightSource,
) -> Result<(LoraConfig, HashMap<String, Tensor>), ModelError> {
    let cfg: LoraConfig = source.read_json("adapter_config.json")?;
    let bad = |path: &std::path::Path, e: candle_core::Error| ModelError::BadWeights {
        path: path.to_path_buf(),
        reason: e.to_string(),
    };
    if let Some(path) = source.resolve_optional("adapter_model.safetensors")? {
        let tensors = candle_core::safetensors::load(&path, &candle_core::Device::Cpu)
            .map_err(|e| bad(&path, e))?;
        return Ok((cfg, tensors));
    }
    if let Some(path) = source.resolve_optional("adapter_model.bin")? {
        return Ok((cfg, crate::weights::read_pth(&path, None)?));
    }
    // Neither: the error names the file PEFT writes today.
    let path = source.resolve("adapter_model.safetensors")?;
    Err(ModelError::BadWeights {
        path,
        reason: "unreadable adapter".into(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::Device;
    use vlmfuse_testkit::rng::SplitMix64 as Rng;
    use vlmfuse_testkit_models::fixtures::RandomTensor;

    fn t(v: &[f32], shape: (usize, usize)) -> Tensor {
        Tensor::from_slice(v, shape, &Device::Cpu).unwrap()
    }

    fn cfg(r: usize, alpha: f64) -> LoraConfig {
        LoraConfig {
            r,
            lora_alpha: alpha,
            use_rslora: false,
            fan_in_fan_out: false,
            use_dora: false,
            alpha_pattern: HashMap::new(),
            rank_pattern: HashMap::new(),
        }
    }

    #[test]
    fn merge_matches_hand_computation() {
        // W0 2x3, rank 1, alpha 4 → scale 4. B·A = [[1],[2]]·[[1,0,-1]] = [[1,0,-1],[2,0,-2]].
        let w0 = t(&[1., 2., 3., 4., 5., 6.], (2, 3));
        let a = t(&[1., 0., -1.], (1, 3));
        let b = t(&[1., 2.], (2, 1));
        let w = merge_lora(&w0, &a, &b, lora_scale(4.0, 1, false), false).unwrap();
        assert_eq!(
            w.to_vec2::<f32>().unwrap(),
            vec![vec![5., 2., -1.], vec![12., 5., -2.]]
        );
        // rsLoRA rank 4, alpha 8 → 8/2 = 4 (vs 2 for plain LoRA).
        assert_eq!(lora_scale(8.0, 4, true), 4.0);
        assert_eq!(lora_scale(8.0, 4, false), 2.0);
    }

    #[test]
    fn merged_linear_equals_unmerged_lora_forward() {
        // The defining property: x·Wᵀ = x·W0ᵀ + s·(x·Aᵀ)·Bᵀ for any x.
        let mut r = Rng::new(3);
        let (out, inp, rank, n) = (7, 5, 3, 4);
        let w0 = r.tensor(&[out, inp], 0.0, 1.0);
        let a = r.tensor(&[rank, inp], 0.0, 1.0);
        let b = r.tensor(&[out, rank], 0.0, 1.0);
        let x = r.tensor(&[n, inp], 0.0, 1.0);
        let s = lora_scale(16.0, rank, false);
        let w = merge_lora(&w0, &a, &b, s, false).unwrap();
        let merged = x.matmul(&w.t().unwrap()).unwrap();
        let lora = (x.matmul(&w0.t().unwrap()).unwrap()
            + (x.matmul(&a.t().unwrap())
                .unwrap()
                .matmul(&b.t().unwrap())
                .unwrap()
                * s)
                .unwrap())
        .unwrap();
        let diff = (merged - lora).unwrap().abs().unwrap().max_all().unwrap();
        assert!(diff.to_scalar::<f32>().unwrap() < 1e-4);

        // fan_in_fan_out stores W transposed; the merge must give the transpose.
        let wt = merge_lora(&w0.t().unwrap().contiguous().unwrap(), &a, &b, s, true).unwrap();
        let d = (wt.t().unwrap() - &w)
            .unwrap()
            .abs()
            .unwrap()
            .max_all()
            .unwrap();
        assert!(d.to_scalar::<f32>().unwrap() < 1e-6);
    }

    #[test]
    fn bf16_base_keeps_dtype() {
        let w0 = t(&[1., 2., 3., 4.], (2, 2)).to_dtype(DType::BF16).unwrap();
        let a = t(&[1., 1.], (1, 2));
        let b = t(&[0.5, 0.5], (2, 1));
        let w = merge_lora(&w0, &a, &b, 2.0, false).unwrap();
        assert_eq!(w.dtype(), DType::BF16);
        let v = w.to_dtype(DType::F32).unwrap().to_vec2::<f32>().unwrap();
        assert_eq!(v, vec![vec![2., 3.], vec![4., 5.]]);
    }

    #[test]
    fn shape_mismatch_is_an_error() {
        let w0 = t(&[0.; 6], (2, 3));
        let a = t(&[0.; 4], (1, 4));
        let b = t(&[0.; 2], (2, 1));
        let e = merge_lora(&w0, &a, &b, 1.0, false).unwrap_err();
        assert!(e.to_string().contains("LoRA shapes"), "{e}");
    }

    #[test]
    fn adapter_keys_map_onto_base_and_patterns_apply() {
        let mut r = Rng::new(9);
        let q = "model.layers.0.self_attn.q_proj";
        let v = "model.layers.0.self_attn.v_proj";
        let mut base = HashMap::new();
        base.insert(format!("{q}.weight"), r.tensor(&[4, 4], 0.0, 1.0));
        base.insert(format!("{v}.weight"), r.tensor(&[4, 4], 0.0, 1.0));
        base.insert("lm_head.weight".to_string(), r.tensor(&[4, 4], 0.0, 1.0));
        let orig = base.clone();
        let mut ad = HashMap::new();
        for m in [q, v] {
            ad.insert(
                format!("base_model.model.{m}.lora_A.weight"),
                r.tensor(&[2, 4], 0.0, 1.0),
            );
            ad.insert(
                format!("base_model.model.{m}.lora_B.weight"),
                r.tensor(&[4, 2], 0.0, 1.0),
            );
        }
        let mut c = cfg(2, 4.0);
        c.alpha_pattern.insert("v_proj".into(), 1.0);
        let keys = merge_adapter(&mut base, &ad, &c).unwrap();
        assert_eq!(keys, vec![format!("{q}.weight"), format!("{v}.weight")]);

        for (m, s) in [(q, 2.0), (v, 0.5)] {
            let a = &ad[&format!("base_model.model.{m}.lora_A.weight")];
            let b = &ad[&format!("base_model.model.{m}.lora_B.weight")];
            let want =
                (&orig[&format!("{m}.weight")] + (b.matmul(a).unwrap() * s).unwrap()).unwrap();
            let d = (&base[&format!("{m}.weight")] - want)
                .unwrap()
                .abs()
                .unwrap()
                .max_all()
                .unwrap();
            assert!(d.to_scalar::<f32>().unwrap() < 1e-5, "{m}");
        }
        let d = (&base["lm_head.weight"] - &orig["lm_head.weight"]).unwrap();
        assert_eq!(
            d.abs()
                .unwrap()
                .max_all()
                .unwrap()
                .to_scalar::<f32>()
                .unwrap(),
            0.0
        );

        // A target missing from the base, and an orphan A, are errors.
        let mut ad2 = HashMap::new();
        ad2.insert(
            "base_model.model.nope.lora_A.weight".to_string(),
            r.tensor(&[2, 4], 0.0, 1.0),
        );
        ad2.insert(
            "base_model.model.nope.lora_B.weight".to_string(),
            r.tensor(&[4, 2], 0.0, 1.0),
        );
        assert!(merge_adapter(&mut base.clone(), &ad2, &c)
            .unwrap_err()
            .to_string()
            .contains("nope"));
        ad2.remove("base_model.model.nope.lora_B.weight");
        assert!(merge_adapter(&mut base, &ad2, &c)
            .unwrap_err()
            .to_string()
            .contains("lora_B"));
    }

    #[test]
    fn adapter_config_parses_peft_json() {
        let j = r#"{"peft_type":"LORA","r":8,"lora_alpha":16,"target_modules":["q_proj"],
                    "use_rslora":false,"fan_in_fan_out":false,"lora_dropout":0.05,"bias":"none"}"#;
        let c: LoraConfig = serde_json::from_str(j).unwrap();
        assert_eq!(c.scale_for("model.layers.0.self_attn.q_proj", 8), 2.0);
    }
}
