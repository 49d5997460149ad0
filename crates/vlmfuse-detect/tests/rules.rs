//! The label rules on synthetic detection sequences (no model): persistence, the path, class
//! mapping, negatives, and what stays unknown.

use vlmfuse_detect::rules::{derive, FrameDetections, LabelRule, RulesConfig};
use vlmfuse_detect::{Detection, TrackerConfig};

const W: u32 = 1280;
const H: u32 = 720;

fn names() -> Vec<String> {
    ["person", "car", "traffic light", "stop sign"]
        .map(String::from)
        .to_vec()
}

fn det(class: usize, x: f32, y: f32, w: f32, h: f32, score: f32) -> Detection {
    Detection {
        xyxy: [x, y, x + w, y + h],
        score,
        class,
    }
}

/// `n` frames at 1 s; `objects(frame)` gives that frame's detections.
fn clip(n: usize, objects: impl Fn(usize) -> Vec<Detection>) -> Vec<FrameDetections> {
    (0..n)
        .map(|i| FrameDetections {
            t_s: i as f64,
            width: W,
            height: H,
            detections: objects(i),
        })
        .collect()
}

fn run(frames: &[FrameDetections]) -> vlmfuse_detect::DetectAnnotation {
    derive(
        frames,
        &names(),
        &TrackerConfig::default(),
        &RulesConfig::default(),
    )
}

#[test]
fn a_light_seen_in_one_frame_is_not_reported_one_that_persists_is() {
    let blip = clip(8, |i| {
        if i == 3 {
            vec![det(2, 620.0, 100.0, 20.0, 50.0, 0.8)]
        } else {
            vec![]
        }
    });
    let a = run(&blip);
    assert_eq!(a.value("traffic_light_ahead"), None, "{a:#?}");
    let why = &a
        .undecided
        .iter()
        .find(|u| u.label == "traffic_light_ahead")
        .unwrap()
        .reason;
    assert!(why.contains("no track persisted"), "{why}");

    let steady = clip(8, |i| {
        if (2..7).contains(&i) {
            vec![det(
                2,
                620.0 + i as f32,
                100.0,
                20.0,
                50.0,
                0.6 + 0.02 * i as f32,
            )]
        } else {
            vec![]
        }
    });
    let a = run(&steady);
    let d = a.get("traffic_light_ahead").expect("decided");
    assert!(d.value);
    let e = &d.evidence[0];
    assert_eq!(
        (e.class.as_str(), e.frames, e.of_frames),
        ("traffic light", 5, 8)
    );
    assert_eq!((e.first_s, e.last_s), (2.0, 6.0));
    assert!((e.mean_score - 0.68).abs() < 1e-5, "{}", e.mean_score);
    assert!((d.confidence - 0.68).abs() < 1e-5);
    // The box where it scored highest: frame 6, the detector's own box.
    assert_eq!((e.best_s, e.best_box), (6.0, [626.0, 100.0, 646.0, 150.0]));
    assert!(e.note.contains("5 of 8 frames"), "{}", e.note);
    // Nothing said about labels whose classes never appeared.
    assert_eq!(a.value("stop"), None);
    assert_eq!(a.value("pedestrian_crossing_ahead"), None);
}

#[test]
fn a_pedestrian_on_the_pavement_is_not_crossing_ahead_one_in_the_path_is() {
    // Walking along the right edge of the frame, feet at y = 650 (x ~ 1180): outside the lane.
    let pavement = clip(8, |i| {
        vec![det(0, 1150.0 + 3.0 * i as f32, 450.0, 50.0, 200.0, 0.85)]
    });
    let a = run(&pavement);
    assert_eq!(a.value("pedestrian_crossing_ahead"), None, "{a:#?}");
    assert!(a
        .undecided
        .iter()
        .any(|u| u.label == "pedestrian_crossing_ahead" && u.reason.contains("in the path")));

    // Crossing from left to right in front of the car, sampled densely enough that the boxes
    // of consecutive frames overlap: in the path for part of the clip.
    let crossing = clip(24, |i| {
        vec![det(0, 20.0 * i as f32, 420.0, 50.0, 200.0, 0.85)]
    });
    let a = run(&crossing);
    let d = a.get("pedestrian_crossing_ahead").expect("decided");
    assert!(d.value);
    assert!(
        d.evidence[0].frames >= 3 && d.evidence[0].frames < 24,
        "{:?}",
        d.evidence[0]
    );
    assert_eq!(a.tracks, 1);

    // The same walk sampled every 80 px: no two boxes overlap, so no track persists (IoU
    // tracking needs frames close enough in time: `[detect] frames`).
    let sparse = clip(8, |i| {
        vec![det(0, 300.0 + 80.0 * i as f32, 420.0, 50.0, 200.0, 0.85)]
    });
    assert_eq!(run(&sparse).value("pedestrian_crossing_ahead"), None);
}

#[test]
fn a_stop_sign_means_stop_and_a_weak_track_does_not() {
    let sign = clip(6, |_| vec![det(3, 900.0, 200.0, 60.0, 60.0, 0.7)]);
    assert_eq!(run(&sign).value("stop"), Some(true));
    // Persistent but below min_score on average.
    let weak = clip(6, |_| vec![det(3, 900.0, 200.0, 60.0, 60.0, 0.26)]);
    assert_eq!(run(&weak).value("stop"), None);
}

#[test]
fn negatives_only_where_the_rule_allows_them_and_too_few_frames_decide_nothing() {
    let empty = clip(8, |_| vec![det(1, 500.0, 400.0, 200.0, 120.0, 0.9)]);
    let mut rules = RulesConfig::default();
    rules.labels[0].negative = true; // traffic_light_ahead
    let a = derive(&empty, &names(), &TrackerConfig::default(), &rules);
    let d = a.get("traffic_light_ahead").unwrap();
    assert!(!d.value);
    assert!((d.confidence - (1.0 - 1.0 / 9.0)).abs() < 1e-12);
    assert_eq!(a.value("stop"), None);

    let short = clip(2, |_| vec![det(2, 620.0, 100.0, 20.0, 50.0, 0.9)]);
    let a = derive(&short, &names(), &TrackerConfig::default(), &rules);
    assert!(a.labels.is_empty());
    assert_eq!(a.undecided.len(), 3);
    assert!(
        a.undecided[0].reason.contains("2 sampled frame"),
        "{:?}",
        a.undecided
    );
}

#[test]
fn another_detectors_class_names_map_through_the_config() {
    // A detector whose classes are "pedestrian" and "signal", mapped by the config.
    let names: Vec<String> = ["pedestrian", "signal"].map(String::from).to_vec();
    let toml_text = r#"
        min_frames = 2
        min_score = 0.5
        path = [[0.0, 1.0], [0.0, 0.0], [1.0, 0.0], [1.0, 1.0]]
        [[labels]]
        label = "traffic_light_ahead"
        classes = ["signal"]
        [[labels]]
        label = "pedestrian_crossing_ahead"
        classes = ["pedestrian"]
        in_path = true
    "#;
    let rules: RulesConfig = toml::from_str(toml_text).unwrap();
    rules.validate().unwrap();
    let frames = clip(3, |_| {
        vec![
            det(1, 10.0, 10.0, 20.0, 40.0, 0.9),
            det(0, 600.0, 400.0, 40.0, 100.0, 0.9),
        ]
    });
    let a = derive(&frames, &names, &TrackerConfig::default(), &rules);
    assert_eq!(a.value("traffic_light_ahead"), Some(true));
    assert_eq!(a.value("pedestrian_crossing_ahead"), Some(true));
    assert_eq!(
        a.get("traffic_light_ahead").unwrap().evidence[0].class,
        "signal"
    );

    // Bad configurations are refused.
    let bad = RulesConfig {
        labels: vec![LabelRule {
            label: "stop".into(),
            classes: vec![],
            in_path: false,
            negative: false,
        }],
        ..Default::default()
    };
    assert!(bad.validate().is_err());
    assert!(toml::from_str::<RulesConfig>("min_frame = 2").is_err());
    let zero = RulesConfig {
        min_frames: 0,
        ..Default::default()
    };
    assert!(zero.validate().is_err());
}
