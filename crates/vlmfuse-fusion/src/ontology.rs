//! The label set. Labels are addressed by index everywhere inside the engine; names appear only
//! at the edges (parsing and output), so another ontology works unchanged.

use serde::{Deserialize, Serialize};
use std::collections::HashMap;

#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Label {
    /// Machine name, as it appears in rounds files and API payloads (`brake`).
    pub id: String,
    /// The paper's words (`brake`, `junction ahead`).
    pub name: String,
    /// A longer gloss for labelers and explanations; optional.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub description: Option<String>,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(from = "Vec<Label>", into = "Vec<Label>")]
pub struct Ontology {
    labels: Vec<Label>,
    index: HashMap<String, usize>,
}

/// The paper's 14 labels in SPEC order (ids 0..13).
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

impl From<Vec<Label>> for Ontology {
    fn from(labels: Vec<Label>) -> Self {
        let mut index = HashMap::new();
        for (i, l) in labels.iter().enumerate() {
            index.entry(l.id.clone()).or_insert(i);
            index.entry(l.name.clone()).or_insert(i);
        }
        Self { labels, index }
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
    /// Builds an ontology, refusing empty sets and duplicate ids or names, which would make a
    /// label ambiguous on the wire.
    pub fn new(labels: Vec<Label>) -> Result<Self, String> {
        if labels.is_empty() {
            return Err("an ontology needs at least one label".into());
        }
        let mut seen = HashMap::new();
        for (i, l) in labels.iter().enumerate() {
            if l.id.trim().is_empty() {
                return Err(format!("label {i} has an empty id"));
            }
            for key in [&l.id, &l.name] {
                if let Some(j) = seen.insert(key.clone(), i) {
                    if j != i {
                        return Err(format!("label name {key:?} is used by labels {j} and {i}"));
                    }
                }
            }
        }
        Ok(Self::from(labels))
    }

    pub fn paper() -> Self {
        Self::from(
            PAPER_LABELS
                .iter()
                .map(|id| Label {
                    id: (*id).to_string(),
                    name: id.replace('_', " "),
                    description: None,
                })
                .collect::<Vec<_>>(),
        )
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

    /// Resolves a label by id or by display name.
    pub fn lookup(&self, name: &str) -> Option<usize> {
        self.index.get(name).copied()
    }

    /// Turns a list of label names into a 0/1 vector, naming the first unknown label.
    pub fn encode<S: AsRef<str>>(&self, names: &[S]) -> Result<Vec<u8>, String> {
        let mut v = vec![0u8; self.len()];
        for n in names {
            let n = n.as_ref();
            match self.lookup(n) {
                Some(k) => v[k] = 1,
                None => return Err(format!("unknown label {n:?}")),
            }
        }
        Ok(v)
    }

    /// The ids of the labels that are on, in ontology order.
    pub fn decode(&self, bits: &[u8]) -> Vec<String> {
        bits.iter()
            .enumerate()
            .filter(|(_, &b)| b != 0)
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
    }

    #[test]
    fn encode_rejects_unknown_and_roundtrips() {
        let o = Ontology::paper();
        let v = o.encode(&["stop", "brake", "stop"]).unwrap();
        assert_eq!(o.decode(&v), vec!["brake", "stop"]);
        assert!(o.encode(&["fly"]).unwrap_err().contains("fly"));
    }

    #[test]
    fn duplicates_are_refused() {
        let l = |id: &str| Label {
            id: id.into(),
            name: id.into(),
            description: None,
        };
        assert!(Ontology::new(vec![l("a"), l("a")]).is_err());
        assert!(Ontology::new(vec![]).is_err());
        assert_eq!(Ontology::new(vec![l("a"), l("b")]).unwrap().len(), 2);
    }
}
