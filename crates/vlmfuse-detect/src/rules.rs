//! Driving labels from persistent tracks: `traffic_light_ahead` (a traffic light),
//! `pedestrian_crossing_ahead` (a person in the vehicle's path) and `stop` (a stop sign), each
//! with its evidence.
//!
//! Why persistence: the detector runs frame by frame and its false positives rarely last, so a
//! label needs one *track* (the same object, [`crate::track`]) seen in at least `min_frames`
//! sampled frames, with a mean score of at least `min_score`. Why a path: a pedestrian on the
//! pavement is not "crossing ahead"; the label needs the person's feet (the bottom centre of
//! the box) inside the path polygon, a trapezoid in normalised image coordinates that a
//! forward dashcam sees the lane ahead in, for `min_frames` of the track's frames.
//!
//! What stays unknown: a label whose classes were detected but never persistently (or never in
//! the path) is undecided, with the reason; so is every label of a clip with fewer sampled
//! frames than `min_frames`. A label whose classes were not detected at all is a negative only
//! when its rule says `negative = true` (off by default: a small detector misses small, far
//! objects, and "I saw none" is weaker evidence than "I saw one"). No I/O here.

use serde::{Deserialize, Serialize};

use crate::decode::Detection;
use crate::track::{TrackOut, Tracker, TrackerConfig};

/// One label rule: which detector classes count, and whether the object must be in the path.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LabelRule {
    /// The ontology's label id.
    pub label: String,
    /// Detector class names (the model's `names`) that count for it.
    pub classes: Vec<String>,
    /// The object's bottom centre must lie in the path polygon.
    #[serde(default)]
    pub in_path: bool,
    /// Report the label as absent when none of its classes is detected in any frame.
    #[serde(default)]
    pub negative: bool,
}

/// The rules' settings (`[detect.rules]`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct RulesConfig {
    /// Frames a track must be seen in (in the path, for path rules).
    pub min_frames: usize,
    /// Lowest mean detection score of such a track.
    pub min_score: f32,
    /// The vehicle's path: a polygon of `[x, y]` points in `[0, 1]` image coordinates (x to the
    /// right, y down), in order around it.
    pub path: Vec<[f64; 2]>,
    pub labels: Vec<LabelRule>,
}

impl Default for RulesConfig {
    /// COCO class names (every ultralytics YOLO trained on COCO), the lane ahead of a centred
    /// forward camera.
    fn default() -> Self {
        Self {
            min_frames: 3,
            min_score: 0.3,
            path: vec![[0.15, 1.0], [0.42, 0.55], [0.58, 0.55], [0.85, 1.0]],
            labels: vec![
                LabelRule {
                    label: "traffic_light_ahead".into(),
                    classes: vec!["traffic light".into()],
                    in_path: false,
                    negative: false,
                },
                LabelRule {
                    label: "pedestrian_crossing_ahead".into(),
                    classes: vec!["person".into()],
                    in_path: true,
                    negative: false,
                },
                LabelRule {
                    label: "stop".into(),
                    classes: vec!["stop sign".into()],
                    in_path: false,
                    negative: false,
                },
            ],
        }
    }
}

impl RulesConfig {
    pub fn validate(&self) -> Result<(), String> {
        if self.min_frames == 0 {
            return Err("min_frames must be at least 1".into());
        }
        if !(0.0..=1.0).contains(&self.min_score) {
            return Err(format!(
                "min_score must be in [0, 1], got {}",
                self.min_score
            ));
        }
        if self.path.len() < 3 {
            return Err("path needs at least 3 points".into());
        }
        if self.path.iter().flatten().any(|v| !v.is_finite()) {
            return Err("path points must be finite".into());
        }
        let mut seen = std::collections::BTreeSet::new();
        for r in &self.labels {
            if r.label.is_empty() || r.classes.is_empty() {
                return Err(format!(
                    "rule {:?} needs a label and at least one class",
                    r.label
                ));
            }
            if !seen.insert(&r.label) {
                return Err(format!("label {:?} has two rules", r.label));
            }
        }
        Ok(())
    }

    /// Whether the bottom centre of `xyxy` in a `w x h` frame is inside the path.
    pub fn in_path(&self, xyxy: &[f32; 4], w: u32, h: u32) -> bool {
        let x = (xyxy[0] as f64 + xyxy[2] as f64) / 2.0 / w as f64;
        let y = xyxy[3] as f64 / h as f64;
        point_in_polygon(x, y, &self.path)
    }
}

/// Even-odd rule; a point on the bottom edge (y = 1) counts as inside.
fn point_in_polygon(x: f64, y: f64, poly: &[[f64; 2]]) -> bool {
    let y = y.min(1.0 - 1e-9);
    let mut inside = false;
    let mut j = poly.len() - 1;
    for i in 0..poly.len() {
        let ([xi, yi], [xj, yj]) = (poly[i], poly[j]);
        if (yi > y) != (yj > y) && x < (xj - xi) * (y - yi) / (yj - yi) + xi {
            inside = !inside;
        }
        j = i;
    }
    inside
}

/// One sampled frame's detections (boxes in the frame's pixels).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct FrameDetections {
    /// Presentation time in the clip.
    pub t_s: f64,
    pub width: u32,
    pub height: u32,
    pub detections: Vec<Detection>,
}

/// Why a label was decided: one track.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TrackEvidence {
    /// The detector's class name.
    pub class: String,
    pub track_id: u64,
    /// Frames the track was seen in (in the path, for path rules), and of how many sampled.
    pub frames: usize,
    pub of_frames: usize,
    /// First and last time it was seen (clip seconds).
    pub first_s: f64,
    pub last_s: f64,
    pub mean_score: f32,
    /// Its box `[x1, y1, x2, y2]` (frame pixels) in the frame where it scored highest, and that
    /// frame's time.
    pub best_box: [f32; 4],
    pub best_s: f64,
    pub note: String,
}

/// A decided label.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Decided {
    pub label: String,
    pub value: bool,
    /// Positives: the best track's mean score; negatives: `1 - 1 / (frames + 1)` (the more
    /// frames without a single detection of the label's classes, the surer).
    pub confidence: f64,
    pub evidence: Vec<TrackEvidence>,
}

/// A label the detections do not decide, and why.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Undecided {
    pub label: String,
    pub reason: String,
}

/// What the detector derived from a clip.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DetectAnnotation {
    /// Sampled frames the detector ran on.
    pub frames: usize,
    /// Detections over all frames (after NMS) and tracks started.
    pub detections: usize,
    pub tracks: usize,
    pub labels: Vec<Decided>,
    pub undecided: Vec<Undecided>,
}

impl DetectAnnotation {
    pub fn get(&self, label: &str) -> Option<&Decided> {
        self.labels.iter().find(|d| d.label == label)
    }
    /// `Some(true/false)` when decided, `None` when unknown.
    pub fn value(&self, label: &str) -> Option<bool> {
        self.get(label).map(|d| d.value)
    }
}

/// A track's sightings: (frame index, output).
type Sightings = Vec<(usize, TrackOut)>;

/// Tracks the frames in order and applies the rules. `names` maps class indices to names.
pub fn derive(
    frames: &[FrameDetections],
    names: &[String],
    tracker: &TrackerConfig,
    rules: &RulesConfig,
) -> DetectAnnotation {
    let mut t = Tracker::new(tracker.clone());
    let mut tracks: std::collections::BTreeMap<u64, Sightings> = Default::default();
    let mut confirmed = std::collections::BTreeSet::new();
    for (fi, f) in frames.iter().enumerate() {
        for o in t.update_all(&f.detections) {
            if o.confirmed {
                confirmed.insert(o.track_id);
            }
            tracks.entry(o.track_id).or_default().push((fi, o));
        }
    }
    // A track never confirmed was one detection that nothing followed.
    tracks.retain(|id, _| confirmed.contains(id));
    let name = |c: usize| names.get(c).cloned().unwrap_or_else(|| c.to_string());
    let detections = frames.iter().map(|f| f.detections.len()).sum();
    let mut out = DetectAnnotation {
        frames: frames.len(),
        detections,
        tracks: tracks.len(),
        labels: Vec::new(),
        undecided: Vec::new(),
    };
    for rule in &rules.labels {
        let counts = |c: usize| rule.classes.contains(&name(c));
        if frames.len() < rules.min_frames {
            out.undecided.push(Undecided {
                label: rule.label.clone(),
                reason: format!(
                    "{} sampled frame(s); a track must persist for {}",
                    frames.len(),
                    rules.min_frames
                ),
            });
            continue;
        }
        let mut evidence = Vec::new();
        let mut seen_brief = 0usize;
        for (&id, sights) in &tracks {
            // The sightings that count: the rule's classes, in the path where required.
            // The path test uses the detection's own box (where the object was seen), not the
            // filter's estimate, which lags a moving object.
            let seen = |fi: usize, o: &TrackOut| {
                frames[fi].detections.get(o.idx).map_or(o.xyxy, |d| d.xyxy)
            };
            let good: Vec<&(usize, TrackOut)> = sights
                .iter()
                .filter(|(fi, o)| {
                    counts(o.class)
                        && (!rule.in_path
                            || rules.in_path(&seen(*fi, o), frames[*fi].width, frames[*fi].height))
                })
                .collect();
            if good.is_empty() {
                continue;
            }
            let mean = good.iter().map(|(_, o)| o.score).sum::<f32>() / good.len() as f32;
            if good.len() < rules.min_frames || mean < rules.min_score {
                seen_brief += 1;
                continue;
            }
            let best = good
                .iter()
                .max_by(|a, b| a.1.score.total_cmp(&b.1.score))
                .copied()
                .unwrap_or(good[0]);
            let bf = &frames[best.0];
            let best_box = seen(best.0, &best.1);
            evidence.push(TrackEvidence {
                class: name(best.1.class),
                track_id: id,
                frames: good.len(),
                of_frames: frames.len(),
                first_s: frames[good[0].0].t_s,
                last_s: frames[good[good.len() - 1].0].t_s,
                mean_score: mean,
                best_box,
                best_s: bf.t_s,
                note: format!(
                    "track {id} ({}) seen in {} of {} frames{}, mean score {mean:.2} (needs {} frames, {:.2})",
                    name(best.1.class),
                    good.len(),
                    frames.len(),
                    if rule.in_path { " in the path" } else { "" },
                    rules.min_frames,
                    rules.min_score
                ),
            });
        }
        if !evidence.is_empty() {
            evidence.sort_by(|a, b| b.mean_score.total_cmp(&a.mean_score));
            out.labels.push(Decided {
                label: rule.label.clone(),
                value: true,
                confidence: evidence[0].mean_score as f64,
                evidence,
            });
            continue;
        }
        let any_detection = frames
            .iter()
            .flat_map(|f| &f.detections)
            .filter(|d| counts(d.class))
            .map(|d| d.score)
            .fold(None, |m: Option<f32>, s| Some(m.map_or(s, |m| m.max(s))));
        match any_detection {
            None if rule.negative => out.labels.push(Decided {
                label: rule.label.clone(),
                value: false,
                confidence: 1.0 - 1.0 / (frames.len() as f64 + 1.0),
                evidence: Vec::new(),
            }),
            None => out.undecided.push(Undecided {
                label: rule.label.clone(),
                reason: format!(
                    "no {} detected in {} frames (absence is not decided: negative = false)",
                    rule.classes.join(" / "),
                    frames.len()
                ),
            }),
            Some(max) => out.undecided.push(Undecided {
                label: rule.label.clone(),
                reason: format!(
                    "{} detected (best score {max:.2}) but no track persisted{} for {} frames \
                     with mean score {:.2} ({} brief track(s))",
                    rule.classes.join(" / "),
                    if rule.in_path { " in the path" } else { "" },
                    rules.min_frames,
                    rules.min_score,
                    seen_brief
                ),
            }),
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_default_path_holds_the_lane_ahead_not_the_pavement() {
        let r = RulesConfig::default();
        // A person at the bottom centre of a 1280x720 frame, and one on the right edge.
        assert!(r.in_path(&[600.0, 500.0, 680.0, 700.0], 1280, 720));
        assert!(r.in_path(&[600.0, 500.0, 680.0, 720.0], 1280, 720));
        assert!(!r.in_path(&[1150.0, 500.0, 1230.0, 700.0], 1280, 720));
        // Above the horizon line of the trapezoid.
        assert!(!r.in_path(&[600.0, 200.0, 680.0, 300.0], 1280, 720));
        r.validate().unwrap();
    }
}
