//! The label set is data, not code: the paper's 14 driving labels are only the default, and every
//! backend must work unchanged for another list.

use crate::LabelerError;
use serde::{Deserialize, Serialize};

/// One label of an ontology.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct LabelDef {
    /// Machine id, the value that appears in reports (e.g. `turn_left`).
    pub id: String,
    /// Human words (e.g. "turn left"); what the models are shown.
    pub name: String,
    /// Optional longer gloss; prompts and prototypes use it when present because display names
    /// alone are often ambiguous ("merge", "stop").
    #[serde(default)]
    pub description: Option<String>,
}

impl LabelDef {
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

/// An ordered, validated list of labels. The order is the order of scores in every output.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(try_from = "Vec<LabelDef>", into = "Vec<LabelDef>")]
pub struct Ontology {
    labels: Vec<LabelDef>,
}

impl TryFrom<Vec<LabelDef>> for Ontology {
    type Error = LabelerError;
    fn try_from(v: Vec<LabelDef>) -> Result<Self, LabelerError> {
        Ontology::new(v)
    }
}

impl From<Ontology> for Vec<LabelDef> {
    fn from(o: Ontology) -> Self {
        o.labels
    }
}

/// The paper's 14 labels, in the order of SPEC section 1 (ids 0..13).
const DEFAULT_LABELS: [(&str, &str, &str); 14] = [
    (
        "turn_left",
        "turn left",
        "turning left at a junction or into another road",
    ),
    (
        "turn_right",
        "turn right",
        "turning right at a junction or into another road",
    ),
    ("brake", "brake", "braking or slowing the vehicle down"),
    ("accelerate", "accelerate", "accelerating or speeding up"),
    ("stop", "stop", "bringing the vehicle to a complete stop"),
    (
        "traffic_light_ahead",
        "traffic light ahead",
        "a traffic light or signal ahead",
    ),
    (
        "junction_ahead",
        "junction ahead",
        "an intersection or junction ahead",
    ),
    (
        "pedestrian_crossing_ahead",
        "pedestrian crossing ahead",
        "a pedestrian crossing, crosswalk or pedestrians crossing ahead",
    ),
    ("merge", "merge", "merging or changing lanes"),
    (
        "maintain_safe_distance",
        "maintain safe distance",
        "keeping a safe distance from the vehicle in front",
    ),
    (
        "check_blind_spot",
        "check blind spot",
        "checking the blind spot or mirrors",
    ),
    (
        "adjust_speed_due_to_weather",
        "adjust speed due to weather",
        "adjusting speed because of rain, fog, snow or ice",
    ),
    (
        "yield_to_traffic",
        "yield to traffic",
        "yielding or giving way to other traffic",
    ),
    (
        "drive_as_normal",
        "drive as normal",
        "continuing to drive normally without any special action",
    ),
];

impl Ontology {
    pub fn new(labels: Vec<LabelDef>) -> Result<Self, LabelerError> {
        if labels.is_empty() {
            return Err(LabelerError::Ontology("no labels".into()));
        }
        let mut seen = std::collections::HashSet::new();
        for l in &labels {
            if l.id.trim().is_empty() || l.name.trim().is_empty() {
                return Err(LabelerError::Ontology(format!(
                    "label with empty id or name: {l:?}"
                )));
            }
            if !seen.insert(l.id.as_str()) {
                return Err(LabelerError::Ontology(format!(
                    "duplicate label id {:?}",
                    l.id
                )));
            }
        }
        Ok(Self { labels })
    }

    /// The paper's 14 driving labels with display names and glosses.
    pub fn default_driving() -> Self {
        Self {
            labels: DEFAULT_LABELS
                .iter()
                .map(|(id, name, desc)| LabelDef::new(id, name, Some(desc)))
                .collect(),
        }
    }

    pub fn labels(&self) -> &[LabelDef] {
        &self.labels
    }

    pub fn len(&self) -> usize {
        self.labels.len()
    }

    pub fn is_empty(&self) -> bool {
        self.labels.is_empty()
    }

    pub fn index_of(&self, id: &str) -> Option<usize> {
        self.labels.iter().position(|l| l.id == id)
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

    pub fn ids(&self) -> impl Iterator<Item = &str> {
        self.labels.iter().map(|l| l.id.as_str())
    }
}
