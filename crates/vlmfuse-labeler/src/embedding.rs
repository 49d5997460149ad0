//! The offline default labeler: sentence embeddings of each clause against label prototypes.
//!
//! Why clauses and prototypes: a VLM answer mixes several labels and negations in one paragraph;
//! one embedding for the whole answer blurs them, while short clauses are close to short
//! paraphrases of one label each. Negation is decided lexically (see `negation`) and matched
//! against the polarity of the prototype, so "avoid following too closely" (a negated form that
//! means "keep a safe distance") still counts, while "no need to brake" does not count as "brake".

use crate::negation::{is_negated, split_clauses};
use crate::{BlockingLabeler, LabelerError, LabelerOutput, Ontology};
use candle_core::{DType, Device, Tensor};
use candle_nn::VarBuilder;
use candle_transformers::models::bert::{BertModel, Config as BertConfig};
use std::collections::HashMap;
use std::path::PathBuf;
use tokenizers::{PaddingParams, Tokenizer, TruncationParams};

/// Paraphrases per default label. Written from how people and VLMs phrase driving advice, not
/// copied from the evaluation data's templates.
const DEFAULT_PROTOTYPES: &[(&str, &[&str])] = &[
    (
        "turn_left",
        &[
            "turn left",
            "make a left turn at the intersection",
            "go left at the junction",
            "take the left road",
            "steer to the left into the side street",
            "hang a left",
            "the route goes left",
        ],
    ),
    (
        "turn_right",
        &[
            "turn right",
            "make a right turn at the intersection",
            "go right at the junction",
            "take the right road",
            "steer to the right into the side street",
            "hang a right",
            "the route goes right",
        ],
    ),
    (
        "brake",
        &[
            "brake",
            "apply the brakes",
            "slow down",
            "decelerate",
            "reduce speed",
            "press the brake pedal gently",
            "ease off the speed",
            "the car ahead is braking",
        ],
    ),
    (
        "accelerate",
        &[
            "accelerate",
            "speed up",
            "increase speed",
            "press the gas pedal",
            "gain speed",
            "go faster to match the traffic",
        ],
    ),
    (
        "stop",
        &[
            "stop",
            "come to a complete stop",
            "stop at the stop line",
            "halt the car",
            "wait at the line until it is clear",
            "the light is red so stop",
            "bring the vehicle to a standstill",
        ],
    ),
    (
        "traffic_light_ahead",
        &[
            "there is a traffic light ahead",
            "a traffic signal is coming up",
            "the light is red",
            "the signal turned green",
            "the traffic lights at the intersection",
            "an amber light ahead",
            "signals hang over the road",
        ],
    ),
    (
        "junction_ahead",
        &[
            "an intersection ahead",
            "approaching a junction",
            "a crossroads is coming up",
            "a side road joins the street",
            "a T-junction",
            "the road forks ahead",
            "a four-way intersection",
        ],
    ),
    (
        "pedestrian_crossing_ahead",
        &[
            "a pedestrian crossing ahead",
            "a crosswalk in front",
            "a zebra crossing",
            "pedestrians are crossing the street",
            "people walking across the road",
            "someone is waiting to cross at the crosswalk",
        ],
    ),
    (
        "merge",
        &[
            "merge into the other lane",
            "change lanes",
            "move into the adjacent lane",
            "merge onto the motorway",
            "the lane ends so merge",
            "join the traffic from the ramp",
            "switch lanes",
        ],
    ),
    (
        "maintain_safe_distance",
        &[
            "keep a safe distance from the car in front",
            "maintain a safe following distance",
            "leave a gap to the vehicle ahead",
            "stay well back from the truck",
            "keep a two second gap",
            "do not tailgate",
            "don't follow too closely",
            "avoid following too closely",
            "avoid following the vehicle in front too closely",
            "don't drive too close to the car ahead",
        ],
    ),
    (
        "check_blind_spot",
        &[
            "check the blind spot",
            "look over the shoulder",
            "check the mirrors",
            "do a shoulder check",
            "make sure the next lane is clear",
            "watch for vehicles beside you",
            "don't forget to check the blind spot",
        ],
    ),
    (
        "adjust_speed_due_to_weather",
        &[
            "slow down because of the rain",
            "reduce speed on the wet road",
            "drive slower in the fog",
            "adapt speed to the snow and ice",
            "drive slowly on the slippery road",
            "lower your speed in the poor visibility",
            "adjust speed for the weather conditions",
        ],
    ),
    (
        "yield_to_traffic",
        &[
            "yield to traffic",
            "give way to other vehicles",
            "let the oncoming cars pass",
            "give priority to traffic on the main road",
            "wait for a gap in the traffic",
            "yield the right of way",
        ],
    ),
    (
        "drive_as_normal",
        &[
            "continue driving normally",
            "proceed as usual",
            "keep going at the same speed",
            "carry on",
            "maintain course and speed",
            "no special action is needed",
            "nothing requires a change",
            "there are no hazards",
        ],
    ),
];

/// Neutral scene statements that belong to no default label. With the clause margin at 0 a clause
/// supports only its best label, so these absorb context sentences ("the road is dry", "it is
/// snowing") that would otherwise drift onto the nearest label (here: the weather label).
const DEFAULT_BACKGROUND: &[&str] = &[
    "the weather is clear and sunny",
    "the road surface is dry",
    "it is raining",
    "it is snowing",
    "the sky is cloudy",
    "there is fog",
    "the car is driving along a city street",
    "we are on a highway",
    "houses and shops line the street",
    "trees along the roadside",
    "a parked bus at the kerb",
    "a cyclist rides in the bike lane",
    "lane markings are painted on the road",
    "street lamps are on",
    "it is night time",
    "a truck is in front of us",
    "scene description",
    "recommended manoeuvre",
    "rationale",
    "safety comes first",
];

/// Per-label thresholds on the cosine similarity for the default ontology, tuned on the training
/// half of `tests/data/labeler/answers.jsonl` with `--example labeler_eval -- --tune`.
const DEFAULT_THRESHOLDS: &[(&str, f32)] = &[
    ("turn_left", 0.70),
    ("turn_right", 0.30),
    ("brake", 0.30),
    ("accelerate", 0.66),
    ("stop", 0.53),
    ("traffic_light_ahead", 0.55),
    ("junction_ahead", 0.67),
    ("pedestrian_crossing_ahead", 0.66),
    ("merge", 0.65),
    ("maintain_safe_distance", 0.64),
    ("check_blind_spot", 0.62),
    ("adjust_speed_due_to_weather", 0.41),
    ("yield_to_traffic", 0.42),
    ("drive_as_normal", 0.53),
];

#[derive(Debug, Clone)]
pub struct EmbeddingConfig {
    /// Directory with `model.safetensors`, `tokenizer.json`, `config.json`.
    pub model_dir: PathBuf,
    /// Cosine threshold for labels without their own.
    pub threshold: f32,
    /// Per-label thresholds (by id). Labels of the default ontology without an entry here use
    /// the values tuned on the training split; other labels use `threshold`.
    pub label_thresholds: HashMap<String, f32>,
    /// A clause only supports labels within this similarity of its best label, so that one clause
    /// ("turn left") does not also vote for a near neighbour ("turn right").
    pub margin: f32,
    /// Extra or replacement paraphrases per label id; labels without any use their display name
    /// and description.
    pub prototypes: HashMap<String, Vec<String>>,
    /// Replace (true) or extend (false) the built-in paraphrases with `prototypes`.
    pub replace_prototypes: bool,
    /// Neutral sentences that belong to no label (see `DEFAULT_BACKGROUND`). `None`: the
    /// built-in list for the default ontology, none for other ontologies (a custom "rain" label
    /// must not be absorbed by "it is raining").
    pub background: Option<Vec<String>>,
}

/// Default global cosine threshold and clause margin (tuned on the training split).
pub const DEFAULT_THRESHOLD: f32 = 0.56;
pub const DEFAULT_MARGIN: f32 = 0.0;

impl EmbeddingConfig {
    pub fn new(model_dir: impl Into<PathBuf>) -> Self {
        Self {
            model_dir: model_dir.into(),
            threshold: DEFAULT_THRESHOLD,
            label_thresholds: HashMap::new(),
            margin: DEFAULT_MARGIN,
            prototypes: HashMap::new(),
            replace_prototypes: false,
            background: None,
        }
    }
}

struct Proto {
    /// Label index, or `None` for a background sentence.
    label: Option<usize>,
    negated: bool,
}

struct Inner {
    model: BertModel,
    tokenizer: Tokenizer,
    device: Device,
    ontology: Ontology,
    protos: Vec<Proto>,
    /// (n_protos, dim), unit rows.
    proto_emb: Tensor,
    thresholds: Vec<f32>,
    margin: f32,
}

/// Similarities of every clause of a text to every label, split by polarity match; the raw
/// material that thresholds and margins act on (kept so tuning does not re-run the model).
#[derive(Debug, Clone)]
pub struct ClauseSims {
    pub clauses: Vec<String>,
    /// `sims[c][k]`: best cosine between clause `c` and a prototype of label `k` of the same
    /// polarity (negated clause vs negated prototype); `f32::NEG_INFINITY` when none.
    pub sims: Vec<Vec<f32>>,
    /// Best similarity of each clause to a background sentence of the same polarity.
    pub background: Vec<f32>,
}

impl ClauseSims {
    /// Label scores: for each label, the best similarity over clauses where it is within `margin`
    /// of that clause's best label.
    pub fn scores(&self, n_labels: usize, margin: f32) -> Vec<f32> {
        let mut out = vec![0f32; n_labels];
        for (row, &bg) in self.sims.iter().zip(&self.background) {
            let best = row.iter().copied().fold(bg, f32::max);
            for (k, &s) in row.iter().enumerate() {
                if s.is_finite() && s >= best - margin && s > out[k] {
                    out[k] = s;
                }
            }
        }
        out
    }
}

pub struct EmbeddingLabeler {
    name: String,
    inner: Inner,
}

impl EmbeddingLabeler {
    /// Loads the model and embeds the prototypes (blocking; call once at start-up).
    pub fn load(ontology: Ontology, cfg: EmbeddingConfig) -> Result<Self, LabelerError> {
        let device = Device::Cpu;
        let f = |n: &str| {
            let p = cfg.model_dir.join(n);
            if p.is_file() {
                Ok(p)
            } else {
                Err(LabelerError::AssetMissing(p.display().to_string()))
            }
        };
        let (weights, tok_path, conf_path) = (
            f("model.safetensors")?,
            f("tokenizer.json")?,
            f("config.json")?,
        );
        let config: BertConfig = serde_json::from_str(&std::fs::read_to_string(conf_path)?)
            .map_err(|e| LabelerError::Model(format!("config.json: {e}")))?;
        // SAFETY: the file is memory-mapped read-only; it must not be modified while loaded,
        // which holds for the asset cache.
        let vb = unsafe { VarBuilder::from_mmaped_safetensors(&[weights], DType::F32, &device)? };
        let model = BertModel::load(vb, &config)?;
        let mut tokenizer =
            Tokenizer::from_file(tok_path).map_err(|e| LabelerError::Tokenizer(e.to_string()))?;
        tokenizer.with_padding(Some(PaddingParams::default()));
        tokenizer
            .with_truncation(Some(TruncationParams {
                max_length: 128,
                ..Default::default()
            }))
            .map_err(|e| LabelerError::Tokenizer(e.to_string()))?;

        for id in cfg.label_thresholds.keys().chain(cfg.prototypes.keys()) {
            if ontology.index_of(id).is_none() {
                return Err(LabelerError::Config(format!(
                    "embedding config names unknown label {id:?}"
                )));
            }
        }
        let builtin: HashMap<&str, &[&str]> = DEFAULT_PROTOTYPES.iter().copied().collect();
        let mut protos = Vec::new();
        let mut texts = Vec::new();
        for (k, l) in ontology.labels().iter().enumerate() {
            let mut list: Vec<String> = Vec::new();
            if !cfg.replace_prototypes {
                if let Some(b) = builtin.get(l.id.as_str()) {
                    list.extend(b.iter().map(|s| s.to_string()));
                }
            }
            if let Some(extra) = cfg.prototypes.get(&l.id) {
                list.extend(extra.iter().cloned());
            }
            if list.is_empty() {
                list.push(l.name.clone());
                if let Some(d) = &l.description {
                    list.push(d.clone());
                }
            }
            for t in list {
                protos.push(Proto {
                    label: Some(k),
                    negated: is_negated(&t),
                });
                texts.push(t.to_lowercase());
            }
        }
        let background: Vec<String> = match &cfg.background {
            Some(b) => b.clone(),
            None if ontology == Ontology::default_driving() => {
                DEFAULT_BACKGROUND.iter().map(|s| s.to_string()).collect()
            }
            None => Vec::new(),
        };
        for t in background {
            protos.push(Proto {
                label: None,
                negated: is_negated(&t),
            });
            texts.push(t.to_lowercase());
        }
        let tuned: HashMap<&str, f32> = if ontology == Ontology::default_driving() {
            DEFAULT_THRESHOLDS.iter().copied().collect()
        } else {
            HashMap::new()
        };
        let thresholds = ontology
            .labels()
            .iter()
            .map(|l| {
                cfg.label_thresholds
                    .get(&l.id)
                    .copied()
                    .or_else(|| tuned.get(l.id.as_str()).copied())
                    .unwrap_or(cfg.threshold)
            })
            .collect();
        let mut inner = Inner {
            model,
            tokenizer,
            device,
            ontology,
            protos,
            proto_emb: Tensor::zeros((1, 1), DType::F32, &Device::Cpu)?,
            thresholds,
            margin: cfg.margin,
        };
        inner.proto_emb = inner.embed(&texts)?;
        Ok(Self {
            name: "embedding:all-MiniLM-L6-v2".into(),
            inner,
        })
    }

    pub fn ontology(&self) -> &Ontology {
        &self.inner.ontology
    }

    /// Clause-level similarities of a text (blocking).
    pub fn clause_sims(&self, text: &str) -> Result<ClauseSims, LabelerError> {
        self.inner.clause_sims(text)
    }
}

impl Inner {
    /// Mean-pooled, L2-normalised sentence embeddings, shape (n, dim).
    fn embed(&self, texts: &[String]) -> Result<Tensor, LabelerError> {
        let enc = self
            .tokenizer
            .encode_batch(texts.to_vec(), true)
            .map_err(|e| LabelerError::Tokenizer(e.to_string()))?;
        let ids: Vec<Tensor> = enc
            .iter()
            .map(|e| Tensor::new(e.get_ids(), &self.device))
            .collect::<Result<_, _>>()?;
        let mask: Vec<Tensor> = enc
            .iter()
            .map(|e| Tensor::new(e.get_attention_mask(), &self.device))
            .collect::<Result<_, _>>()?;
        let ids = Tensor::stack(&ids, 0)?;
        let mask = Tensor::stack(&mask, 0)?;
        let type_ids = ids.zeros_like()?;
        let hidden = self.model.forward(&ids, &type_ids, Some(&mask))?;
        let m = mask.to_dtype(DType::F32)?.unsqueeze(2)?;
        let summed = hidden.broadcast_mul(&m)?.sum(1)?;
        let counts = m.sum(1)?.clamp(1e-9, f64::MAX)?;
        let mean = summed.broadcast_div(&counts)?;
        let norm = mean.sqr()?.sum_keepdim(1)?.sqrt()?.clamp(1e-12, f64::MAX)?;
        Ok(mean.broadcast_div(&norm)?)
    }

    fn clause_sims(&self, text: &str) -> Result<ClauseSims, LabelerError> {
        let clauses = split_clauses(text);
        let n_labels = self.ontology.len();
        if clauses.is_empty() {
            return Ok(ClauseSims {
                clauses,
                sims: Vec::new(),
                background: Vec::new(),
            });
        }
        let emb = self.embed(&clauses)?;
        let sim: Vec<Vec<f32>> = emb.matmul(&self.proto_emb.t()?)?.to_vec2()?;
        let mut sims = Vec::with_capacity(clauses.len());
        let mut background = Vec::with_capacity(clauses.len());
        for (c, row) in clauses.iter().zip(sim) {
            let neg = is_negated(c);
            let mut best = vec![f32::NEG_INFINITY; n_labels];
            let mut bg = f32::NEG_INFINITY;
            for (p, s) in self.protos.iter().zip(row) {
                if p.negated != neg {
                    continue;
                }
                let slot = match p.label {
                    Some(k) => &mut best[k],
                    None => &mut bg,
                };
                if s > *slot {
                    *slot = s;
                }
            }
            sims.push(best);
            background.push(bg);
        }
        Ok(ClauseSims {
            clauses,
            sims,
            background,
        })
    }

    fn label(&self, text: &str) -> Result<LabelerOutput, LabelerError> {
        let cs = self.clause_sims(text)?;
        let scores = cs.scores(self.ontology.len(), self.margin);
        Ok(LabelerOutput::thresholded(
            &self.ontology,
            &scores,
            &self.thresholds,
        ))
    }
}

impl BlockingLabeler for EmbeddingLabeler {
    fn name(&self) -> &str {
        &self.name
    }

    fn label_blocking(&self, text: &str) -> Result<LabelerOutput, LabelerError> {
        self.inner.label(text)
    }
}
