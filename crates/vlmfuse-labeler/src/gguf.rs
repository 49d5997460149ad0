//! Labeler backed by a small in-process GGUF LLM (gemma-3-270m, a base model).
//!
//! A base model does not follow instructions, so it is not asked to produce JSON. Instead each
//! label is a yes/no question and the score is the model's own preference for " yes" over " no"
//! as the next token. The description and the question stem are shared by all labels, so their
//! key/value cache is computed once per text and reused for every label's short suffix.
//!
//! Two corrections make the raw preference usable:
//! * content-free calibration (Zhao et al., 2021): small LMs have a strong per-question bias
//!   towards "yes" or "no", so the log-odds for an empty description are subtracted;
//! * the suffix is fed one token at a time: candle 0.11.1's `quantized_gemma3` masks out the
//!   cached positions when a multi-token chunk is processed at `index_pos > 0`, while a single
//!   token attends to the whole cache. A test checks this path against a full forward pass.

use crate::sp_tokenizer::SpTokenizer;
use crate::{BlockingLabeler, LabelerError, LabelerOutput, Ontology};
use candle_core::quantized::gguf_file;
use candle_core::{Device, Tensor};
use candle_transformers::models::quantized_gemma3::ModelWeights;
use std::collections::HashMap;
use std::path::PathBuf;

#[derive(Debug, Clone)]
pub struct GgufConfig {
    pub model_path: PathBuf,
    /// Threshold on the calibrated yes-probability for labels without their own.
    pub threshold: f32,
    pub label_thresholds: HashMap<String, f32>,
    /// Subtract each question's log-odds on a content-free description.
    pub calibrate: bool,
    /// Longer descriptions keep their first tokens only: the sliding-window layers (512 tokens)
    /// would otherwise see a different context on the single-token path than in training.
    pub max_text_tokens: usize,
}

/// Default threshold on the calibrated yes-probability (tuned on the training split).
pub const DEFAULT_GGUF_THRESHOLD: f32 = 0.5;

impl GgufConfig {
    pub fn new(model_path: impl Into<PathBuf>) -> Self {
        Self {
            model_path: model_path.into(),
            threshold: DEFAULT_GGUF_THRESHOLD,
            label_thresholds: HashMap::new(),
            calibrate: true,
            max_text_tokens: 384,
        }
    }
}

const PREFIX_HEAD: &str = "Driving description: ";
const PREFIX_TAIL: &str = "\nQuestion: Does the description recommend or mention";
const SUFFIX_TAIL: &str = "? Answer:";
const CONTENT_FREE: &str = "N/A";

struct Inner {
    base: ModelWeights,
    tok: SpTokenizer,
    device: Device,
    ontology: Ontology,
    /// Token ids of each label's question suffix, e.g. " turning left? Answer:".
    suffixes: Vec<Vec<u32>>,
    yes_ids: Vec<u32>,
    no_ids: Vec<u32>,
    calib: Vec<f32>,
    thresholds: Vec<f32>,
    max_text_tokens: usize,
}

pub struct GgufLabeler {
    name: String,
    inner: Inner,
}

fn log_sum_exp(xs: &[f32]) -> f32 {
    let m = xs.iter().copied().fold(f32::NEG_INFINITY, f32::max);
    m + xs.iter().map(|x| (x - m).exp()).sum::<f32>().ln()
}

impl GgufLabeler {
    /// Loads the GGUF and runs the calibration pass (blocking; seconds).
    pub fn load(ontology: Ontology, cfg: GgufConfig) -> Result<Self, LabelerError> {
        if !cfg.model_path.is_file() {
            return Err(LabelerError::AssetMissing(
                cfg.model_path.display().to_string(),
            ));
        }
        for id in cfg.label_thresholds.keys() {
            if ontology.index_of(id).is_none() {
                return Err(LabelerError::Config(format!(
                    "gguf config names unknown label {id:?}"
                )));
            }
        }
        let device = Device::Cpu;
        let mut file = std::fs::File::open(&cfg.model_path)?;
        let ct = gguf_file::Content::read(&mut file).map_err(|e| e.with_path(&cfg.model_path))?;
        let tok = SpTokenizer::from_gguf(&ct)?;
        let base = ModelWeights::from_gguf(ct, &mut file, &device)?;
        let ids = |pieces: &[&str]| -> Vec<u32> {
            pieces.iter().filter_map(|p| tok.piece_id(p)).collect()
        };
        let yes_ids = ids(&["\u{2581}yes", "\u{2581}Yes"]);
        let no_ids = ids(&["\u{2581}no", "\u{2581}No"]);
        if yes_ids.is_empty() || no_ids.is_empty() {
            return Err(LabelerError::Tokenizer(
                "vocabulary has no \u{2581}yes/\u{2581}no pieces".into(),
            ));
        }
        let suffixes = ontology
            .labels()
            .iter()
            .map(|l| tok.encode(&format!(" {}{SUFFIX_TAIL}", l.gloss())))
            .collect();
        let thresholds = ontology
            .labels()
            .iter()
            .map(|l| {
                cfg.label_thresholds
                    .get(&l.id)
                    .copied()
                    .unwrap_or(cfg.threshold)
            })
            .collect();
        let mut inner = Inner {
            base,
            tok,
            device,
            calib: vec![0.0; ontology.len()],
            ontology,
            suffixes,
            yes_ids,
            no_ids,
            thresholds,
            max_text_tokens: cfg.max_text_tokens,
        };
        if cfg.calibrate {
            inner.calib = inner.log_odds(CONTENT_FREE, true)?;
        }
        Ok(Self {
            name: "gguf:gemma-3-270m".into(),
            inner,
        })
    }

    pub fn ontology(&self) -> &Ontology {
        &self.inner.ontology
    }

    pub fn tokenizer(&self) -> &SpTokenizer {
        &self.inner.tok
    }

    /// Uncalibrated yes-vs-no log-odds per label (blocking). `reuse_prefix = false` runs one full
    /// forward pass per label; it exists to check the cached path and costs several times more.
    pub fn raw_log_odds(&self, text: &str, reuse_prefix: bool) -> Result<Vec<f32>, LabelerError> {
        self.inner.log_odds(text, reuse_prefix)
    }
}

impl Inner {
    fn prefix_ids(&self, text: &str) -> Vec<u32> {
        let mut ids: Vec<u32> = self.tok.bos_id().into_iter().collect();
        ids.extend(self.tok.encode(PREFIX_HEAD));
        let mut body = self.tok.encode(text.trim());
        body.truncate(self.max_text_tokens);
        ids.extend(body);
        ids.extend(self.tok.encode(PREFIX_TAIL));
        ids
    }

    fn yes_no(&self, logits: &Tensor) -> Result<f32, LabelerError> {
        let v: Vec<f32> = logits.squeeze(0)?.to_vec1()?;
        let pick = |ids: &[u32]| ids.iter().map(|&i| v[i as usize]).collect::<Vec<_>>();
        Ok(log_sum_exp(&pick(&self.yes_ids)) - log_sum_exp(&pick(&self.no_ids)))
    }

    fn log_odds(&self, text: &str, reuse_prefix: bool) -> Result<Vec<f32>, LabelerError> {
        let prefix = self.prefix_ids(text);
        let n = prefix.len();
        if reuse_prefix {
            let mut primed = self.base.clone();
            primed.forward(
                &Tensor::new(prefix.as_slice(), &self.device)?.unsqueeze(0)?,
                0,
            )?;
            self.suffixes
                .iter()
                .map(|suf| {
                    // Cloning shares the weights and the cached prefix (tensors are refcounted).
                    let mut m = primed.clone();
                    let mut logits = None;
                    for (j, &t) in suf.iter().enumerate() {
                        let x = Tensor::new(&[[t]], &self.device)?;
                        logits = Some(m.forward(&x, n + j)?);
                    }
                    let logits =
                        logits.ok_or_else(|| LabelerError::Model("empty suffix".into()))?;
                    self.yes_no(&logits)
                })
                .collect()
        } else {
            self.suffixes
                .iter()
                .map(|suf| {
                    let mut m = self.base.clone();
                    let all: Vec<u32> = prefix.iter().chain(suf).copied().collect();
                    let logits =
                        m.forward(&Tensor::new(all.as_slice(), &self.device)?.unsqueeze(0)?, 0)?;
                    self.yes_no(&logits)
                })
                .collect()
        }
    }

    fn label(&self, text: &str) -> Result<LabelerOutput, LabelerError> {
        let raw = self.log_odds(text, true)?;
        let scores: Vec<f32> = raw
            .iter()
            .zip(&self.calib)
            .map(|(r, c)| 1.0 / (1.0 + (-(r - c)).exp()))
            .collect();
        Ok(LabelerOutput::thresholded(
            &self.ontology,
            &scores,
            &self.thresholds,
        ))
    }
}

impl BlockingLabeler for GgufLabeler {
    fn name(&self) -> &str {
        &self.name
    }

    fn label_blocking(&self, text: &str) -> Result<LabelerOutput, LabelerError> {
        self.inner.label(text)
    }
}
