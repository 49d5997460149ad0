//! The labelers' evaluation: data set loading, metrics and threshold tuning shared by the
//! labeler's tests and its `labeler_eval` example, so that both report the same numbers.

use anyhow::Context;
use serde::Deserialize;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use vlmfuse_core::{Ontology, OntologyError};
use vlmfuse_labeler::assets::AssetPaths;
use vlmfuse_labeler::{
    BlockingLabeler, EmbeddingConfig, EmbeddingLabeler, LabelerError, LabelerOutput,
    OnnxEncoderConfig, OnnxSentenceEncoder,
};

/// Answers per round in the labeler's evaluation and benchmarks. The service labels a round's
/// answers (one per reporter) in one `label_batch` call; five reporters is a large round, and
/// the ~30 ms target of the label stage is per round.
pub const ROUND_ANSWERS: usize = 5;

/// The embedding labeler that `labeler_eval` scores, as `config/default.toml` serves it: the
/// paper's labels with their glosses, the default settings, and the fetched MiniLM on the ONNX
/// Runtime encoder (`encoder = "onnx"`, all cores). The service's test holds its served
/// labeler to this one's labels.
pub fn eval_embedding_labeler(assets: &AssetPaths) -> Result<EmbeddingLabeler, LabelerError> {
    let mut enc = OnnxEncoderConfig::new(&assets.minilm_onnx_dir);
    enc.session.library = Some(assets.onnxruntime.clone());
    EmbeddingLabeler::with_encoder(
        Ontology::default_driving(),
        EmbeddingConfig::new(&assets.minilm_onnx_dir),
        Arc::new(OnnxSentenceEncoder::load(&enc)?),
    )
}

/// The same matcher on the candle encoder (`encoder = "candle"`).
pub fn eval_candle_labeler(assets: &AssetPaths) -> Result<EmbeddingLabeler, LabelerError> {
    EmbeddingLabeler::load(
        Ontology::default_driving(),
        EmbeddingConfig::new(&assets.minilm_dir),
    )
}

/// Labels `texts` in rounds of [`ROUND_ANSWERS`], one `label_batch_blocking` call per round,
/// as `/v1/infer` labels a round.
pub fn label_in_rounds<L: BlockingLabeler + ?Sized>(
    labeler: &L,
    texts: &[&str],
) -> Result<Vec<LabelerOutput>, LabelerError> {
    let mut out = Vec::with_capacity(texts.len());
    for round in texts.chunks(ROUND_ANSWERS) {
        out.extend(labeler.label_batch_blocking(round)?);
    }
    Ok(out)
}

/// The held-out answers (`split == "test"`), in file order: never used for tuning.
pub fn test_split(data: &[Example]) -> Vec<&Example> {
    data.iter().filter(|e| e.split == "test").collect()
}

/// One labelled VLM answer.
#[derive(Debug, Clone, Deserialize)]
pub struct Example {
    pub id: String,
    pub split: String,
    pub text: String,
    pub labels: Vec<String>,
    /// The answer's layout (`three_step`, `one_liner`, `json`, …): for per-style scores.
    #[serde(default)]
    pub style: String,
}

/// `tests/data/labeler/answers.jsonl` in this source tree.
pub fn default_dataset_path() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../tests/data/labeler/answers.jsonl")
}

/// `tests/data/labeler/answers_styles.jsonl`: the second labelled set, in the styles other than
/// the paper's three-step answer (terse, lists, JSON, captions, negation- and hedge-heavy,
/// lower case with typos), by two more annotators.
pub fn styles_dataset_path() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../tests/data/labeler/answers_styles.jsonl")
}

pub fn load_dataset(path: &Path) -> anyhow::Result<Vec<Example>> {
    let text = std::fs::read_to_string(path).with_context(|| path.display().to_string())?;
    text.lines()
        .filter(|l| !l.trim().is_empty())
        .enumerate()
        .map(|(i, l)| {
            serde_json::from_str(l).with_context(|| format!("{}:{}", path.display(), i + 1))
        })
        .collect()
}

/// Converts label ids to a 0/1 vector in ontology order; unknown ids are an error because a
/// silently dropped truth label would inflate the scores.
pub fn to_mask(ontology: &Ontology, ids: &[String]) -> Result<Vec<bool>, OntologyError> {
    let mut m = vec![false; ontology.len()];
    for id in ids {
        let k = ontology
            .index_of(id)
            .ok_or_else(|| OntologyError::UnknownLabel(id.clone()))?;
        m[k] = true;
    }
    Ok(m)
}

/// Micro- and macro-F1 (PAPER-METHOD.md §7: a label with no true and no predicted positive scores
/// F1 = 1 in the macro mean).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct F1 {
    pub micro: f64,
    pub macro_: f64,
}

pub fn f1_scores(truth: &[Vec<bool>], pred: &[Vec<bool>]) -> F1 {
    let l = truth.first().map_or(0, Vec::len);
    let (mut tp, mut fp, mut fnn) = (vec![0usize; l], vec![0usize; l], vec![0usize; l]);
    for (t, p) in truth.iter().zip(pred) {
        for k in 0..l {
            match (t[k], p[k]) {
                (true, true) => tp[k] += 1,
                (false, true) => fp[k] += 1,
                (true, false) => fnn[k] += 1,
                _ => {}
            }
        }
    }
    let f = |tp: usize, fp: usize, fnn: usize| {
        if tp + fp + fnn == 0 {
            1.0
        } else {
            2.0 * tp as f64 / (2 * tp + fp + fnn) as f64
        }
    };
    let (stp, sfp, sfn) = (tp.iter().sum(), fp.iter().sum(), fnn.iter().sum());
    let macro_ = if l == 0 {
        1.0
    } else {
        (0..l).map(|k| f(tp[k], fp[k], fnn[k])).sum::<f64>() / l as f64
    };
    F1 {
        micro: f(stp, sfp, sfn),
        macro_,
    }
}

/// F1 of each label on its own (ontology order), for per-label tables and the "no label below"
/// target.
pub fn per_label_f1(truth: &[Vec<bool>], pred: &[Vec<bool>]) -> Vec<f64> {
    let l = truth.first().map_or(0, Vec::len);
    (0..l)
        .map(|k| {
            let col = |m: &[Vec<bool>]| m.iter().map(|r| vec![r[k]]).collect::<Vec<_>>();
            f1_scores(&col(truth), &col(pred)).micro
        })
        .collect()
}

/// Per-label F1 for one column of scores at a threshold.
pub fn label_f1(scores: &[f32], truth: &[bool], t: f32) -> f64 {
    let (mut tp, mut fp, mut fnn) = (0, 0, 0);
    for (&s, &y) in scores.iter().zip(truth) {
        match (y, s >= t) {
            (true, true) => tp += 1,
            (false, true) => fp += 1,
            (true, false) => fnn += 1,
            _ => {}
        }
    }
    if tp + fp + fnn == 0 {
        1.0
    } else {
        2.0 * tp as f64 / (2 * tp + fp + fnn) as f64
    }
}

/// Chooses one global threshold that maximises micro-F1 over `grid`, then per-label thresholds
/// for labels with at least `min_pos` positives (fewer positives over-fit; those keep the global
/// one). Ties go to the lowest threshold. Returns (global, per-label).
pub fn tune_thresholds(
    scores: &[Vec<f32>],
    truth: &[Vec<bool>],
    grid: &[f32],
    min_pos: usize,
) -> (f32, Vec<f32>) {
    let l = truth.first().map_or(0, Vec::len);
    let mut best = (f64::MIN, grid[0]);
    for &t in grid {
        let pred: Vec<Vec<bool>> = scores
            .iter()
            .map(|r| r.iter().map(|&s| s >= t).collect())
            .collect();
        let m = f1_scores(truth, &pred).micro;
        if m > best.0 + 1e-12 {
            best = (m, t);
        }
    }
    let global = best.1;
    let per = (0..l)
        .map(|k| {
            let col: Vec<f32> = scores.iter().map(|r| r[k]).collect();
            let y: Vec<bool> = truth.iter().map(|r| r[k]).collect();
            if y.iter().filter(|&&b| b).count() < min_pos {
                return global;
            }
            let mut b = (f64::MIN, global);
            for &t in grid {
                let f = label_f1(&col, &y, t);
                if f > b.0 + 1e-12 {
                    b = (f, t);
                }
            }
            b.1
        })
        .collect();
    (global, per)
}
