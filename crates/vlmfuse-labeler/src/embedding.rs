//! The offline default labeler: the annotation guidelines' rules, plus sentence embeddings for
//! the paraphrases the rules do not list.
//!
//! How a round is labelled (`label_batch`):
//! 1. Every answer is read into sentences and items (`text`), and the rules (`rules`) find the
//!    mentions of the default labels with their negation, hedge and agent scopes.
//! 2. The advice items (imperatives, "you should ...") that no rule explained, and every item
//!    for labels the rules do not know, are embedded, all answers together, in **one** encoder
//!    call, and compared with paraphrase
//!    prototypes of each label. A prototype only matches an item of the same polarity, and a
//!    hedged item or another road user's action matches nothing.
//! 3. A label is on when a rule says so, or when its best item similarity reaches the label's
//!    threshold and beats the neutral background sentences. Labels that the guidelines define
//!    by their words (brake, turns, marked crossings, give-way wording, weather as the reason,
//!    and the scene nouns of G6) are left to the rules alone: an embedding cannot tell "stop"
//!    from "slow down", or "keep left" from "turn left", which is exactly what those rules are
//!    about.
//!
//! Why embed only unexplained advice items: an item the rules read ("no need to stop") is
//! decided, a description ("trees line the road") carries no manoeuvre, and the encoder is the
//! cost of the stage (about 4 ms per short item on two cores): a round has ~30 items, ~14 with
//! no rule mention, and a few of those are advice.

use crate::rules::{self, Kind, Mention};
use crate::text::{self, Sentence, Speller};
use crate::{
    BlockingLabeler, Evidence, EvidenceSource, LabelerError, LabelerOutput, Ontology,
    SentenceEncoder,
};
use std::collections::HashMap;
use std::path::PathBuf;
use std::sync::Arc;
use vlmfuse_models::text::CandleEncoder;

/// Paraphrases per default label. Written from how people and VLMs phrase driving advice, not
/// copied from the evaluation data.
const DEFAULT_PROTOTYPES: &[(&str, &[&str])] = &[
    (
        "accelerate",
        &[
            "speed up",
            "increase your speed",
            "go faster to match the traffic",
            "get up to the speed limit",
            "pick up the pace",
        ],
    ),
    (
        "stop",
        &[
            "come to a complete stop",
            "stop at the line",
            "bring the vehicle to a standstill",
            "wait at the line until it is clear",
            "halt the car",
        ],
    ),
    (
        "merge",
        &[
            "merge into the other lane",
            "change lanes",
            "move into the adjacent lane",
            "merge onto the motorway",
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
            "do not tailgate",
            "don't follow too closely",
        ],
    ),
    (
        "check_blind_spot",
        &[
            "check the blind spot",
            "look over your shoulder",
            "check the mirrors",
            "make sure the next lane is clear",
            "glance behind before moving over",
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
        ],
    ),
];

/// Neutral scene statements that belong to no default label: an item must be closer to a label
/// than to all of these.
const DEFAULT_BACKGROUND: &[&str] = &[
    "the weather is clear and sunny",
    "the road surface is dry",
    "it is raining",
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
    "pedestrians are walking on the pavement",
    "safety comes first",
    "other road users should be watched",
];

/// Labels the guidelines define by their words; embeddings never turn them on.
/// The scene labels are also named by the nouns the guidelines list (G6), so only manoeuvre
/// labels take paraphrases.
const RULE_ONLY: &[&str] = &[
    "turn_left",
    "turn_right",
    "brake",
    "pedestrian_crossing_ahead",
    "yield_to_traffic",
    "adjust_speed_due_to_weather",
    "traffic_light_ahead",
    "junction_ahead",
];

/// Cosine thresholds for the embedding-eligible default labels. Tuned on the training split
/// (`--example labeler_eval -- --tune`): there the rules already read every paraphrase the
/// annotators used, and a paraphrase match over an item the rules left unexplained was right in
/// 3 of 63 cases at cosine 0.65 and in none of 6 above 0.75. The rule used to set them: the lowest
/// threshold at which the train split's additions are more often right than wrong, else 0.90,
/// where only near-verbatim paraphrases match (none on train). Custom labels, which the rules
/// do not know, use `EmbeddingConfig::threshold`.
const DEFAULT_THRESHOLDS: &[(&str, f32)] = &[
    ("accelerate", 0.90),
    ("stop", 0.90),
    ("merge", 0.90),
    ("maintain_safe_distance", 0.90),
    ("check_blind_spot", 0.90),
    ("drive_as_normal", 0.90),
];

#[derive(Debug, Clone)]
pub struct EmbeddingConfig {
    /// Directory with `model.safetensors`, `tokenizer.json`, `config.json` (the candle engine);
    /// its `tokenizer.json` also gives the speller its word list, whatever the engine.
    pub model_dir: PathBuf,
    /// Cosine threshold for labels without their own.
    pub threshold: f32,
    /// Per-label thresholds (by id); labels of the default ontology without an entry use the
    /// tuned values.
    pub label_thresholds: HashMap<String, f32>,
    /// Extra or replacement paraphrases per label id; labels without any use their display name
    /// and description.
    pub prototypes: HashMap<String, Vec<String>>,
    /// Replace (true) or extend (false) the built-in paraphrases with `prototypes`.
    pub replace_prototypes: bool,
    /// Neutral sentences that belong to no label. `None`: the built-in list when the ontology
    /// uses default ids, none otherwise (a custom "rain" label must not be absorbed by "it is
    /// raining").
    pub background: Option<Vec<String>>,
    /// Apply the guideline rules to the labels whose ids they know (turn off to compare).
    pub rules: bool,
}

/// Default cosine threshold for labels without a tuned one (custom ontologies).
pub const DEFAULT_THRESHOLD: f32 = 0.56;

impl EmbeddingConfig {
    pub fn new(model_dir: impl Into<PathBuf>) -> Self {
        Self {
            model_dir: model_dir.into(),
            threshold: DEFAULT_THRESHOLD,
            label_thresholds: HashMap::new(),
            prototypes: HashMap::new(),
            replace_prototypes: false,
            background: None,
            rules: true,
        }
    }
}

struct Proto {
    /// Label index, or `None` for a background sentence.
    label: Option<usize>,
    negated: bool,
    emb: Vec<f32>,
}

/// The best paraphrase match of one label in one answer.
#[derive(Debug, Clone, PartialEq)]
pub struct ItemMatch {
    /// The item's text (normalised).
    pub item: String,
    pub score: f32,
    /// Best background similarity of that item.
    pub background: f32,
}

/// Everything the labeler read in one answer, before thresholds: kept so that tuning and
/// explanations do not re-run the model.
#[derive(Debug, Clone)]
pub struct Reading {
    pub sentences: Vec<Sentence>,
    pub mentions: Vec<Mention>,
    /// Per ontology label: the rule decision (None when the rules do not know the label) and
    /// the deciding mention.
    pub rule: Vec<Option<(bool, Option<usize>)>>,
    /// Per ontology label: the best item match (polarity-checked), if any item was embedded.
    pub best: Vec<Option<ItemMatch>>,
}

struct Inner {
    encoder: Arc<dyn SentenceEncoder>,
    ontology: Ontology,
    speller: Speller,
    protos: Vec<Proto>,
    thresholds: Vec<f32>,
    /// Per label: the rules know it.
    ruled: Vec<bool>,
    /// Per label: embeddings may turn it on.
    eligible: Vec<bool>,
    /// Index of drive_as_normal and of the labels that exclude it (a change of plan).
    normal: Option<usize>,
    changes: Vec<usize>,
}

pub struct EmbeddingLabeler {
    name: String,
    inner: Inner,
}

fn dot(a: &[f32], b: &[f32]) -> f32 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

fn speller_for(cfg: &EmbeddingConfig) -> Speller {
    let p = cfg.model_dir.join("tokenizer.json");
    let Ok(t) = std::fs::read_to_string(&p) else {
        return Speller::default();
    };
    let Ok(v) = serde_json::from_str::<serde_json::Value>(&t) else {
        return Speller::default();
    };
    match v.pointer("/model/vocab").and_then(|v| v.as_object()) {
        Some(m) => Speller::with_words(
            m.keys()
                .filter(|w| w.len() > 2 && w.chars().all(|c| c.is_ascii_lowercase()))
                .cloned(),
        ),
        None => Speller::default(),
    }
}

impl EmbeddingLabeler {
    /// Loads the candle sentence encoder from `cfg.model_dir` and embeds the prototypes
    /// (blocking; call once at start-up).
    pub fn load(ontology: Ontology, cfg: EmbeddingConfig) -> Result<Self, LabelerError> {
        let enc = CandleEncoder::load(&cfg.model_dir)?;
        Self::with_encoder(ontology, cfg, Arc::new(enc))
    }

    /// Builds the labeler on any encoder engine (candle, ONNX Runtime): the matcher is the same.
    pub fn with_encoder(
        ontology: Ontology,
        cfg: EmbeddingConfig,
        encoder: Arc<dyn SentenceEncoder>,
    ) -> Result<Self, LabelerError> {
        for id in cfg.label_thresholds.keys().chain(cfg.prototypes.keys()) {
            if ontology.index_of(id).is_none() {
                return Err(LabelerError::Config(format!(
                    "embedding config names unknown label {id:?}"
                )));
            }
        }
        if !(0.0..=1.0).contains(&cfg.threshold) {
            return Err(LabelerError::Config(format!(
                "embedding threshold {} is not in [0, 1]",
                cfg.threshold
            )));
        }
        let rule_ids: Vec<&str> = rules::rule_ids().collect();
        let ruled: Vec<bool> = ontology
            .labels()
            .iter()
            .map(|l| cfg.rules && rule_ids.contains(&l.id.as_str()))
            .collect();
        let eligible: Vec<bool> = ontology
            .labels()
            .iter()
            .zip(&ruled)
            .map(|(l, &r)| !(r && RULE_ONLY.contains(&l.id.as_str())))
            .collect();
        let builtin: HashMap<&str, &[&str]> = DEFAULT_PROTOTYPES.iter().copied().collect();
        let mut texts: Vec<(Option<usize>, String)> = Vec::new();
        for (k, l) in ontology.labels().iter().enumerate() {
            if !eligible[k] {
                continue;
            }
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
            texts.extend(list.into_iter().map(|t| (Some(k), t)));
        }
        let uses_defaults = ontology
            .ids()
            .any(|id| Ontology::default_driving().index_of(id).is_some());
        let background: Vec<String> = match &cfg.background {
            Some(b) => b.clone(),
            None if uses_defaults => DEFAULT_BACKGROUND.iter().map(|s| s.to_string()).collect(),
            None => Vec::new(),
        };
        texts.extend(background.into_iter().map(|t| (None, t)));
        let speller = speller_for(&cfg);
        let norm: Vec<String> = texts.iter().map(|(_, t)| text::normalize(t)).collect();
        let refs: Vec<&str> = norm.iter().map(String::as_str).collect();
        let embs = encoder.encode(&refs)?;
        let protos = texts
            .iter()
            .zip(&norm)
            .zip(embs)
            .map(|(((label, _), n), emb)| {
                let s = text::sentences(n);
                let negated = s.first().is_some_and(|s| {
                    let (neg, _, _) = rules::item_polarity(s, 0, s.words.len());
                    neg
                });
                Proto {
                    label: *label,
                    negated,
                    emb,
                }
            })
            .collect();
        let tuned: HashMap<&str, f32> = DEFAULT_THRESHOLDS.iter().copied().collect();
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
        let normal = ontology.index_of("drive_as_normal").filter(|&k| ruled[k]);
        let changes = [
            "brake",
            "accelerate",
            "stop",
            "turn_left",
            "turn_right",
            "merge",
            "yield_to_traffic",
            "adjust_speed_due_to_weather",
        ]
        .iter()
        .filter_map(|id| ontology.index_of(id))
        .collect();
        Ok(Self {
            name: format!("embedding:{}", encoder.engine()),
            inner: Inner {
                encoder,
                ontology,
                speller,
                protos,
                thresholds,
                ruled,
                eligible,
                normal,
                changes,
            },
        })
    }

    pub fn ontology(&self) -> &Ontology {
        &self.inner.ontology
    }

    /// The thresholds in use, in ontology order.
    pub fn thresholds(&self) -> &[f32] {
        &self.inner.thresholds
    }

    /// What the labeler read in each text, before thresholds (blocking; one encoder call).
    pub fn read_batch(&self, texts: &[&str]) -> Result<Vec<Reading>, LabelerError> {
        self.inner.read_batch(texts)
    }

    /// Labels with explicit thresholds (for tuning).
    pub fn decide_with(&self, r: &Reading, thresholds: &[f32]) -> LabelerOutput {
        self.inner.decide(r, thresholds)
    }
}

impl Inner {
    fn read_batch(&self, texts: &[&str]) -> Result<Vec<Reading>, LabelerError> {
        let n = self.ontology.len();
        let mut readings = Vec::with_capacity(texts.len());
        // (reading, sentence, item range, polarity) of every item to embed.
        let mut queue: Vec<(usize, usize, (usize, usize), bool)> = Vec::new();
        let mut item_texts: Vec<String> = Vec::new();
        let any_free = self
            .eligible
            .iter()
            .zip(&self.ruled)
            .any(|(&e, &r)| e && !r);
        for (ti, t) in texts.iter().enumerate() {
            let sentences = text::sentences_with(t, &self.speller);
            let mentions = if self.ruled.iter().any(|&r| r) {
                rules::mentions(&sentences)
            } else {
                Vec::new()
            };
            let decided = rules::decide(&sentences, &mentions);
            let rule: Vec<Option<(bool, Option<usize>)>> = self
                .ontology
                .labels()
                .iter()
                .zip(&self.ruled)
                .map(|(l, &r)| {
                    if !r {
                        return None;
                    }
                    decided.iter().find(|d| d.0 == l.id).map(|d| (d.1, d.2))
                })
                .collect();
            for (si, s) in sentences.iter().enumerate() {
                for (a, b) in rules::items(s) {
                    if b - a < 2 {
                        continue;
                    }
                    let explained = mentions
                        .iter()
                        .any(|m| m.sentence == si && m.a < b && a < m.b);
                    // Labels the rules know: only advice items that no rule read (see the module
                    // docs); labels they do not know: every item.
                    if !any_free && (explained || !rules::advice_item(s, a, b)) {
                        continue;
                    }
                    let (neg, hedged, other) = rules::item_polarity(s, a, b);
                    if hedged || other {
                        continue;
                    }
                    let words: Vec<&str> = (a..b).map(|k| s.w(k)).collect();
                    queue.push((ti, si, (a, b), neg));
                    item_texts.push(words.join(" "));
                }
            }
            readings.push(Reading {
                sentences,
                mentions,
                rule,
                best: vec![None; n],
            });
        }
        // One encoder call for every item of every answer; identical items are encoded once.
        let mut uniq: Vec<&str> = item_texts.iter().map(String::as_str).collect();
        uniq.sort_unstable();
        uniq.dedup();
        let embs = self.encoder.encode(&uniq)?;
        let index: HashMap<&str, usize> = uniq.iter().enumerate().map(|(i, t)| (*t, i)).collect();
        for ((ti, _si, _span, neg), item) in queue.iter().zip(&item_texts) {
            let e = &embs[index[item.as_str()]];
            let mut best = vec![f32::NEG_INFINITY; n];
            let mut bg = f32::NEG_INFINITY;
            for p in &self.protos {
                if p.negated != *neg {
                    continue;
                }
                let s = dot(e, &p.emb);
                match p.label {
                    Some(k) => best[k] = best[k].max(s),
                    None => bg = bg.max(s),
                }
            }
            let r = &mut readings[*ti];
            for (slot, &score) in r.best.iter_mut().zip(&best) {
                if score.is_finite() && slot.as_ref().is_none_or(|m| score > m.score) {
                    *slot = Some(ItemMatch {
                        item: item.clone(),
                        score,
                        background: bg,
                    });
                }
            }
        }
        Ok(readings)
    }

    fn decide(&self, r: &Reading, thresholds: &[f32]) -> LabelerOutput {
        let n = self.ontology.len();
        let mut on = vec![false; n];
        let mut scores = vec![0f32; n];
        let mut evidence = Vec::new();
        let mut rule_on = vec![false; n];
        for k in 0..n {
            let id = &self.ontology.labels()[k].id;
            if let Some((true, m)) = r.rule[k] {
                on[k] = true;
                rule_on[k] = true;
                scores[k] = 1.0;
                if let Some(m) = m.and_then(|i| r.mentions.get(i)) {
                    evidence.push(rule_evidence(id, r, m, true));
                }
            } else if let Some(m) = r.best[k].as_ref() {
                scores[k] = m.score.max(0.0);
                let ok = self.eligible[k]
                    && m.score >= thresholds[k]
                    && m.score > m.background
                    // A rule that read a negated or hedged mention of this label vetoes a
                    // paraphrase match.
                    && !r.mentions.iter().any(|x| x.label == id && !x.positive());
                if ok {
                    on[k] = true;
                    evidence.push(Evidence {
                        label: id.clone(),
                        clause: m.item.clone(),
                        score: m.score,
                        negated: false,
                        hedged: false,
                        source: EvidenceSource::Embedding,
                        accepted: true,
                    });
                }
            }
            if !on[k] {
                // Show the mentions that were read and discounted.
                if let Some(m) = r
                    .mentions
                    .iter()
                    .find(|x| x.label == id && (x.negated || x.hedged || x.other))
                {
                    evidence.push(rule_evidence(id, r, m, false));
                }
            }
        }
        // drive_as_normal is off whenever any change of plan is on (guidelines).
        if let Some(dn) = self.normal {
            if on[dn] && self.changes.iter().any(|&c| on[c]) {
                on[dn] = false;
                for e in evidence.iter_mut().filter(|e| e.label == "drive_as_normal") {
                    e.accepted = false;
                }
            }
        }
        let mut out = LabelerOutput::from_decisions(&self.ontology, &scores, &on);
        evidence.sort_by_key(|e| self.ontology.index_of(&e.label));
        out.evidence = evidence;
        out
    }

    fn label_batch(&self, texts: &[&str]) -> Result<Vec<LabelerOutput>, LabelerError> {
        let rs = self.read_batch(texts)?;
        Ok(rs
            .iter()
            .map(|r| self.decide(r, &self.thresholds))
            .collect())
    }
}

fn rule_evidence(id: &str, r: &Reading, m: &Mention, accepted: bool) -> Evidence {
    let s = &r.sentences[m.sentence];
    Evidence {
        label: id.to_string(),
        clause: s.original.clone(),
        score: if accepted { 1.0 } else { 0.0 },
        negated: m.negated && m.kind != Kind::Inverted || m.kind == Kind::Denial,
        hedged: m.hedged,
        source: EvidenceSource::Rule,
        accepted,
    }
}

impl BlockingLabeler for EmbeddingLabeler {
    fn name(&self) -> &str {
        &self.name
    }

    fn label_blocking(&self, text: &str) -> Result<LabelerOutput, LabelerError> {
        let mut out = self.inner.label_batch(&[text])?;
        out.pop()
            .ok_or_else(|| LabelerError::Internal("no output for the text".into()))
    }

    /// Every clause of every text in one encoder pass (the round's answers together).
    fn label_batch_blocking(&self, texts: &[&str]) -> Result<Vec<LabelerOutput>, LabelerError> {
        self.inner.label_batch(texts)
    }

    /// One pass of milliseconds: not worth stopping halfway, and splitting it per text would
    /// give up the single encoder call.
    fn label_batch_cancellable(
        &self,
        texts: &[&str],
        _cancel: &std::sync::atomic::AtomicBool,
    ) -> Result<Vec<LabelerOutput>, LabelerError> {
        self.inner.label_batch(texts)
    }
}
