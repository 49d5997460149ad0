//! The label set. Labels are addressed by index everywhere inside the engine and the labelers;
//! names appear only at the edges (parsing and output), so another ontology works unchanged.
//!
//! One type serves the fusion engine (which needs exact id/name lookup on the wire) and the
//! labelers (which need the descriptions models are shown, and a lenient lookup for what LLMs
//! echo back). Before, each crate had its own copy, and the service translated between them.

use serde::{Deserialize, Serialize};
use std::collections::HashMap;

/// One label of an ontology.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Label {
    /// Machine name, as it appears in rounds files and API payloads (`brake`).
    pub id: String,
    /// The paper's words (`brake`, `junction ahead`); also accepted on the wire.
    pub name: String,
    /// A longer gloss for labelers and explanations; optional, because display names alone are
    /// often ambiguous ("merge", "stop") but not every deployment writes glosses.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub description: Option<String>,
}

impl Label {
    pub fn new(id: &str, name: &str, description: Option<&str>) -> Self {
        Self {
            id: id.to_string(),
            name: name.to_string(),
            description: description.map(str::to_string),
        }
    }

    /// The phrase models see: the description when there is one, else the display name.
    pub fn gloss(&self) -> &str {
        self.description.as_deref().unwrap_or(&self.name)
    }
}

/// Why a list of labels is not an ontology, or a name is not in it.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum OntologyError {
    #[error("an ontology needs at least one label")]
    Empty,
    #[error("label {0} has an empty id")]
    EmptyId(usize),
    #[error("label {0} has an empty name")]
    EmptyName(usize),
    /// An id or name used twice would make a label ambiguous on the wire.
    #[error("label name {key:?} is used by labels {first} and {second}")]
    Duplicate {
        key: String,
        first: usize,
        second: usize,
    },
    #[error("unknown label {0:?}")]
    UnknownLabel(String),
}

/// An ordered, validated list of labels. The order is the index order of the engine and the
/// order of scores in every labeler output.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(try_from = "Vec<Label>", into = "Vec<Label>")]
pub struct Ontology {
    labels: Vec<Label>,
    /// Id and display name -> index.
    index: HashMap<String, usize>,
}

/// The paper's 14 labels in docs/PAPER-METHOD.md order (ids 0..13).
pub const PAPER_LABELS: [&str; 14] = [
    "turn_left",
    "turn_right",
    "brake",
    "accelerate",
    "stop",
    "traffic_light_ahead",
    "junction_ahead",
    "pedestrian_crossing_ahead",
    "merge",
    "maintain_safe_distance",
    "check_blind_spot",
    "adjust_speed_due_to_weather",
    "yield_to_traffic",
    "drive_as_normal",
];

/// Glosses of the paper's labels, in [`PAPER_LABELS`] order: what a labeler shows a model.
const PAPER_DESCRIPTIONS: [&str; 14] = [
    "turning left at a junction or into another road",
    "turning right at a junction or into another road",
    "braking or slowing the vehicle down",
    "accelerating or speeding up",
    "bringing the vehicle to a complete stop",
    "a traffic light or signal ahead",
    "an intersection or junction ahead",
    "a pedestrian crossing, crosswalk or pedestrians crossing ahead",
    "merging or changing lanes",
    "keeping a safe distance from the vehicle in front",
    "checking the blind spot or mirrors",
    "adjusting speed because of rain, fog, snow or ice",
    "yielding or giving way to other traffic",
    "continuing to drive normally without any special action",
];

impl TryFrom<Vec<Label>> for Ontology {
    type Error = OntologyError;
    fn try_from(v: Vec<Label>) -> Result<Self, OntologyError> {
        Ontology::new(v)
    }
}

impl From<Ontology> for Vec<Label> {
    fn from(o: Ontology) -> Self {
        o.labels
    }
}

impl Default for Ontology {
    fn default() -> Self {
        Self::paper()
    }
}

impl Ontology {
    /// Builds an ontology, refusing empty sets, empty ids or names, and an id or name used by two
    /// labels, which would make a label ambiguous on the wire.
    pub fn new(labels: Vec<Label>) -> Result<Self, OntologyError> {
        if labels.is_empty() {
            return Err(OntologyError::Empty);
        }
        let mut index = HashMap::new();
        for (i, l) in labels.iter().enumerate() {
            if l.id.trim().is_empty() {
                return Err(OntologyError::EmptyId(i));
            }
            if l.name.trim().is_empty() {
                return Err(OntologyError::EmptyName(i));
            }
            for key in [&l.id, &l.name] {
                if let Some(j) = index.insert(key.clone(), i) {
                    if j != i {
                        return Err(OntologyError::Duplicate {
                            key: key.clone(),
                            first: j,
                            second: i,
                        });
                    }
                }
            }
        }
        Ok(Self { labels, index })
    }

    fn from_table(descriptions: bool) -> Self {
        let labels = PAPER_LABELS
            .iter()
            .zip(PAPER_DESCRIPTIONS)
            .map(|(id, d)| Label::new(id, &id.replace('_', " "), descriptions.then_some(d)))
            .collect();
        Self::new(labels).expect("the paper's labels are a valid ontology")
    }

    /// The paper's 14 labels (PAPER-METHOD.md §1): ids and display names, no descriptions. The service's
    /// default (`config/default.toml`).
    pub fn paper() -> Self {
        Self::from_table(false)
    }

    /// The paper's 14 labels with a gloss each: what the labelers are tuned and evaluated on.
    pub fn default_driving() -> Self {
        Self::from_table(true)
    }

    pub fn len(&self) -> usize {
        self.labels.len()
    }

    pub fn is_empty(&self) -> bool {
        self.labels.is_empty()
    }

    pub fn labels(&self) -> &[Label] {
        &self.labels
    }

    pub fn id(&self, k: usize) -> &str {
        &self.labels[k].id
    }

    pub fn ids(&self) -> impl Iterator<Item = &str> {
        self.labels.iter().map(|l| l.id.as_str())
    }

    /// Resolves a label by id or by display name, exactly (the wire format).
    pub fn lookup(&self, name: &str) -> Option<usize> {
        self.index.get(name).copied()
    }

    /// Resolves a label by id only.
    pub fn index_of(&self, id: &str) -> Option<usize> {
        self.index
            .get(id)
            .copied()
            .filter(|&k| self.labels[k].id == id)
    }

    /// Accepts an id or, case-insensitively, a display name: LLMs often echo the words they were
    /// shown instead of the id, and that is unambiguous.
    pub fn resolve(&self, s: &str) -> Option<usize> {
        let t = s.trim();
        self.index_of(t).or_else(|| {
            self.labels
                .iter()
                .position(|l| l.name.eq_ignore_ascii_case(t) || l.id.eq_ignore_ascii_case(t))
        })
    }

    /// Turns a list of label names into a 0/1 vector, naming the first unknown label.
    pub fn encode<S: AsRef<str>>(&self, names: &[S]) -> Result<Vec<u8>, OntologyError> {
        let mut v = vec![0u8; self.len()];
        for n in names {
            let n = n.as_ref();
            match self.lookup(n) {
                Some(k) => v[k] = 1,
                None => return Err(OntologyError::UnknownLabel(n.to_string())),
            }
        }
        Ok(v)
    }

    /// The ids of the labels that are on, in ontology order.
    pub fn decode(&self, bits: &[u8]) -> Vec<String> {
        // 1 only: a truth vector marks labels of unknown truth 2 (partial feedback).
        bits.iter()
            .enumerate()
            .filter(|(_, &b)| b == 1)
            .map(|(k, _)| self.labels[k].id.clone())
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn paper_ontology_has_spec_order_and_names() {
        let o = Ontology::paper();
        assert_eq!(o.len(), 14);
        assert_eq!(o.id(2), "brake");
        assert_eq!(o.id(13), "drive_as_normal");
        assert_eq!(o.lookup("junction ahead"), Some(6));
        assert_eq!(o.lookup("junction_ahead"), Some(6));
        assert_eq!(o.lookup("Junction ahead"), None);
        assert_eq!(o.resolve(" Junction Ahead "), Some(6));
        assert_eq!(o.index_of("junction ahead"), None);
        assert!(o.labels().iter().all(|l| l.description.is_none()));
    }

    #[test]
    fn the_driving_ontology_is_the_paper_one_with_glosses() {
        let (p, d) = (Ontology::paper(), Ontology::default_driving());
        assert_eq!(p.ids().collect::<Vec<_>>(), d.ids().collect::<Vec<_>>());
        assert_ne!(p, d);
        assert_eq!(d.labels()[2].gloss(), "braking or slowing the vehicle down");
        assert_eq!(p.labels()[2].gloss(), "brake");
    }

    #[test]
    fn encode_rejects_unknown_and_roundtrips() {
        let o = Ontology::paper();
        let v = o.encode(&["stop", "brake", "stop"]).unwrap();
        assert_eq!(o.decode(&v), vec!["brake", "stop"]);
        assert!(o.encode(&["fly"]).unwrap_err().to_string().contains("fly"));
    }

    #[test]
    fn duplicates_are_refused() {
        let l = |id: &str| Label::new(id, id, None);
        assert!(Ontology::new(vec![l("a"), l("a")]).is_err());
        assert!(Ontology::new(vec![]).is_err());
        assert!(Ontology::new(vec![Label::new("a", " ", None)]).is_err());
        assert_eq!(Ontology::new(vec![l("a"), l("b")]).unwrap().len(), 2);
        // Deserialising validates too.
        let bad: Result<Ontology, _> =
            serde_json::from_str(r#"[{"id": "a", "name": "x"}, {"id": "b", "name": "x"}]"#);
        assert!(bad.is_err());
    }
}
