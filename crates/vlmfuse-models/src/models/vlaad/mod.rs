//! VLAAD (sungyeonparkk/vision-assistant-for-driving) in process, in Video-LLaMA's layout: EVA
//! ViT-g and BLIP-2's Q-Former per frame (32 queries each), learned frame positions added, a
//! 2-layer video Q-Former over all frames' queries, `llama_proj` into LLaMA-2, whose prompt
//! carries the clip's 32 tokens where `<ImageHere>` stood.
//!
//! Loads the files a VLAAD release consists of, named in `config.json` ([`config`]): the
//! fine-tuned run's `.pth` (`{"model": …}`: `video_Qformer`, `video_query_tokens`,
//! `video_frame_position_embedding`, `llama_proj`), BLIP-2's `.pth` (`Qformer`,
//! `query_tokens`, `ln_vision`, and `visual_encoder` when it has it), EVA ViT-g's `.pth` (flat),
//! and the LLaMA directory. A PEFT LoRA adapter on the LLaMA is merged at load. Later files
//! override earlier ones as `load_state_dict(strict=False)` does in the repository: ViT, then
//! BLIP-2, then the run.

pub mod config;
pub mod family;
pub mod processor;
pub mod towers;

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use candle_core::{DType, Device, Tensor};
use candle_nn::VarBuilder;

pub use config::VlaadConfig;
pub use family::VlaadFamily;
pub use processor::{ClipPixels, VlaadProcessor, VISUAL_TOKEN};

use crate::models::common::{self, load_merged, splice_visual};
use crate::models::video_llava::bad_weights;
use crate::models::video_llava::config::TextConfig;
use crate::models::video_llava::processor::EncodedBatch;
use crate::models::video_llava::text::{KvCache, LlamaText};
use crate::weights::{read_pth, WeightSource};
use crate::ModelError;
use towers::{EvaVit, Qformer};

/// Model inputs: left-padded ids with [`VISUAL_TOKEN`] runs, and each row's clip.
#[derive(Debug, Clone, PartialEq)]
pub struct ModelInputs {
    pub ids: EncodedBatch,
    pub videos: Vec<ClipPixels>,
}

pub use crate::models::common::LoadOptions;

/// A file named in `config.json`: relative to the checkpoint (through its source, so hub
/// checkpoints work), or absolute.
fn locate(source: &WeightSource, name: &str) -> Result<PathBuf, ModelError> {
    let p = Path::new(name);
    if p.is_absolute() {
        if p.exists() {
            return Ok(p.to_path_buf());
        }
        return Err(ModelError::MissingWeights {
            file: name.to_string(),
            searched: vec![p.to_path_buf()],
        });
    }
    source.resolve(name)
}

/// The LLaMA directory: relative to a local checkpoint, absolute, or a hub id.
fn llama_source(source: &WeightSource, name: &str) -> WeightSource {
    let p = Path::new(name);
    if p.is_absolute() {
        return WeightSource::local(p);
    }
    if let WeightSource::Local { path } = source {
        let d = path.join(name);
        if d.join("config.json").is_file() {
            return WeightSource::local(d);
        }
    }
    WeightSource::parse(name)
}

/// A loaded VLAAD.
pub struct Vlaad {
    cfg: VlaadConfig,
    text_cfg: TextConfig,
    vit: EvaVit,
    ln_vision: candle_nn::LayerNorm,
    qformer: Qformer,
    query_tokens: Tensor,
    frame_pos: Tensor,
    video_qformer: Qformer,
    video_query_tokens: Tensor,
    llama_proj: candle_nn::Linear,
    text: LlamaText,
    device: Device,
    dtype: DType,
    merged_lora: Vec<String>,
    llama: WeightSource,
}

impl Vlaad {
    /// Reads `config.json`, the three `.pth` files and the LLaMA. Blocking; call at start-up.
    pub fn load(source: &WeightSource, opts: &LoadOptions) -> Result<Self, ModelError> {
        let raw: serde_json::Value = source.read_json("config.json")?;
        let cfg = VlaadConfig::from_json(&raw)?;
        let llama = llama_source(source, &cfg.llama_model);
        let lraw: serde_json::Value = llama.read_json("config.json")?;
        let text_cfg = TextConfig::llama_json(&lraw)?;
        let tie = lraw
            .get("tie_word_embeddings")
            .and_then(|x| x.as_bool())
            .unwrap_or(false);

        // The visual side: ViT, then BLIP-2, then the run, later files overriding.
        let mut vis: HashMap<String, Tensor> = HashMap::new();
        if let Some(v) = &cfg.vit_model {
            let p = locate(source, v)?;
            for (k, t) in read_pth(&p, None)? {
                vis.insert(format!("visual_encoder.{k}"), t);
            }
        }
        let blip = locate(source, &cfg.q_former_model)?;
        vis.extend(read_pth(&blip, Some("model"))?);
        let run = locate(source, &cfg.ckpt)?;
        vis.extend(read_pth(&run, Some("model"))?);
        let vis = vis
            .into_iter()
            .map(|(k, t)| Ok((k, t.to_dtype(opts.dtype)?.to_device(&opts.device)?)))
            .collect::<Result<HashMap<_, _>, candle_core::Error>>()?;
        let vvb = VarBuilder::from_tensors(vis, opts.dtype, &opts.device);
        let err = bad_weights(&run);
        if !vvb.contains_tensor("visual_encoder.cls_token") {
            return Err(ModelError::BadWeights {
                path: blip.clone(),
                reason: "no EVA ViT weights (`visual_encoder.*`): name vit_model in config.json"
                    .into(),
            });
        }
        let (e, q) = (&cfg.vit, &cfg.qformer);
        let vit = EvaVit::load(vvb.pp("visual_encoder"), e, cfg.img_size).map_err(&err)?;
        let ln_vision =
            candle_nn::layer_norm(e.embed_dim, 1e-5, vvb.pp("ln_vision")).map_err(&err)?;
        let qformer = Qformer::load(
            vvb.pp("Qformer").pp("bert"),
            q,
            q.num_hidden_layers,
            q.cross_attention_freq,
            e.embed_dim,
        )
        .map_err(&err)?;
        let query_tokens = vvb
            .get((1, cfg.num_query_token, q.hidden_size), "query_tokens")
            .map_err(&err)?;
        let frame_pos = vvb
            .pp("video_frame_position_embedding")
            .get((cfg.max_frame_pos, q.hidden_size), "weight")
            .map_err(&err)?;
        let video_qformer = Qformer::load(
            vvb.pp("video_Qformer").pp("bert"),
            q,
            cfg.video_qformer_layers,
            1,
            q.hidden_size,
        )
        .map_err(&err)?;
        let video_query_tokens = vvb
            .get(
                (1, cfg.num_video_query_token, q.hidden_size),
                "video_query_tokens",
            )
            .map_err(&err)?;
        let llama_proj =
            candle_nn::linear(q.hidden_size, text_cfg.hidden_size, vvb.pp("llama_proj"))
                .map_err(&err)?;

        // The LLaMA, with the adapter merged if there is one.
        let files = llama.safetensors_files()?;
        let first = files.first().cloned().unwrap_or_default();
        let (tvb, merged_lora) = load_merged(
            &files,
            opts.adapter.as_ref(),
            HashMap::new(),
            |k| k.to_string(),
            opts.dtype,
            &opts.device,
        )?;
        let head = if tie {
            None
        } else if tvb.contains_tensor("lm_head.weight") {
            Some(tvb.pp("lm_head"))
        } else {
            return Err(ModelError::BadWeights {
                path: first,
                reason: "no `lm_head.weight` and tie_word_embeddings is false".into(),
            });
        };
        let text =
            LlamaText::load(tvb.pp("model"), head, &text_cfg).map_err(bad_weights(&first))?;
        Ok(Self {
            cfg,
            text_cfg,
            vit,
            ln_vision,
            qformer,
            query_tokens,
            frame_pos,
            video_qformer,
            video_query_tokens,
            llama_proj,
            text,
            device: opts.device.clone(),
            dtype: opts.dtype,
            merged_lora,
            llama,
        })
    }

    pub fn config(&self) -> &VlaadConfig {
        &self.cfg
    }
    pub fn text_config(&self) -> &TextConfig {
        &self.text_cfg
    }
    /// Where the LLaMA (and so the tokenizer) comes from.
    pub fn llama_source(&self) -> &WeightSource {
        &self.llama
    }
    pub fn device(&self) -> &Device {
        &self.device
    }
    pub fn dtype(&self) -> DType {
        self.dtype
    }
    pub fn merged_lora_keys(&self) -> &[String] {
        &self.merged_lora
    }
    pub fn new_cache(&self, capacity: usize) -> KvCache {
        self.text.new_cache(capacity)
    }

    /// `encode_videoQformer_visual` for one clip: `[num_video_query_token, llama hidden]`.
    pub fn clip_tokens(&self, v: &ClipPixels) -> Result<Tensor, ModelError> {
        let s = self.cfg.img_size;
        if v.size != s {
            return Err(ModelError::InvalidInput(format!(
                "a clip preprocessed to {0}x{0}, but the ViT takes {s}x{s}",
                v.size
            )));
        }
        if v.frames > self.cfg.max_frame_pos {
            return Err(ModelError::InvalidInput(format!(
                "{} frames, but the model has {} frame positions",
                v.frames, self.cfg.max_frame_pos
            )));
        }
        let t = v.frames;
        let px = Tensor::from_slice(&v.data, (t, 3, s, s), &self.device)?.to_dtype(self.dtype)?;
        let img = candle_nn::Module::forward(&self.ln_vision, &self.vit.forward(&px)?)?;
        let h = self.cfg.qformer.hidden_size;
        let nq = self.cfg.num_query_token;
        let q = self.query_tokens.expand((t, nq, h))?.contiguous()?;
        let frames = self.qformer.forward(&q, &img)?;
        let frames = frames.broadcast_add(&self.frame_pos.narrow(0, 0, t)?.unsqueeze(1)?)?;
        let frames = frames.reshape((1, t * nq, h))?;
        let vq = self.video_query_tokens.contiguous()?;
        let video = self.video_qformer.forward(&vq, &frames)?;
        Ok(candle_nn::Module::forward(&self.llama_proj, &video)?.squeeze(0)?)
    }

    /// Input embeddings with each row's [`VISUAL_TOKEN`] run replaced by its clip's tokens.
    pub fn input_embeddings(&self, inputs: &ModelInputs) -> Result<Tensor, ModelError> {
        splice_visual(&self.text, &inputs.ids, || {
            let feats = inputs
                .videos
                .iter()
                .map(|v| self.clip_tokens(v))
                .collect::<Result<Vec<_>, _>>()?;
            Ok(Tensor::cat(&feats, 0)?)
        })
    }

    pub fn prefill(&self, inputs: &ModelInputs, cache: &mut KvCache) -> Result<Tensor, ModelError> {
        cache.reset();
        let emb = self.input_embeddings(inputs)?;
        Ok(self.text.forward(&emb, &inputs.ids.attention_mask, cache)?)
    }

    pub fn step(&self, tokens: &[u32], cache: &mut KvCache) -> Result<Tensor, ModelError> {
        common::step(&self.text, tokens, cache)
    }
}
