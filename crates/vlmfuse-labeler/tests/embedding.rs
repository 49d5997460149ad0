//! The embedding labeler (guideline rules + all-MiniLM-L6-v2) with the real model: the issue's
//! examples, evidence, batching, custom ontologies, and floors on the held-out test split.

mod common;

use std::sync::{Arc, Mutex, OnceLock};
use vlmfuse_labeler::{
    BackendPool, BlockingLabeler, EmbeddingConfig, EmbeddingLabeler, EvidenceSource, Label,
    Labeler, Ontology, PoolConfig, SentenceEncoder,
};
use vlmfuse_testkit_models::labeler_eval::{
    default_dataset_path, f1_scores, load_dataset, styles_dataset_path, to_mask,
};

fn labeler() -> &'static Arc<EmbeddingLabeler> {
    static L: OnceLock<Arc<EmbeddingLabeler>> = OnceLock::new();
    L.get_or_init(|| {
        let a = common::assets();
        Arc::new(
            EmbeddingLabeler::load(
                Ontology::default_driving(),
                EmbeddingConfig::new(&a.minilm_dir),
            )
            .expect("load embedding labeler"),
        )
    })
}

fn labels(text: &str) -> Vec<String> {
    labeler().label_blocking(text).unwrap().labels
}

/// Every `(text, labels)` case labelled as given (labels in any order), all failures listed.
fn assert_cases(cases: &[(&str, &[&str])]) {
    let onto = Ontology::default_driving();
    let mut failures = Vec::new();
    for (text, want) in cases {
        let mut want: Vec<String> = want.iter().map(|s| s.to_string()).collect();
        want.sort_by_key(|id| onto.index_of(id));
        let got = labels(text);
        if got != want {
            failures.push(format!("{text:?}: got {got:?}, want {want:?}"));
        }
    }
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}

/// The served labeler on the test split of `data` (in rounds of `round` answers) against
/// floors: at least `min_answers` answers, micro-F1, macro-F1 and every label's F1.
fn assert_floors(
    data: &std::path::Path,
    what: &str,
    round: usize,
    min_answers: usize,
    (micro, macro_, label): (f64, f64, f64),
) {
    let l = labeler();
    let onto = Ontology::default_driving();
    let data = load_dataset(data).unwrap();
    let test: Vec<_> = data.iter().filter(|e| e.split == "test").collect();
    assert!(test.len() >= min_answers, "{} test answers", test.len());
    let truth: Vec<_> = test
        .iter()
        .map(|e| to_mask(&onto, &e.labels).unwrap())
        .collect();
    let texts: Vec<&str> = test.iter().map(|e| e.text.as_str()).collect();
    let mut pred = Vec::new();
    for chunk in texts.chunks(round) {
        for o in l.label_batch_blocking(chunk).unwrap() {
            pred.push(to_mask(&onto, &o.labels).unwrap());
        }
    }
    let f = f1_scores(&truth, &pred);
    eprintln!(
        "embedding labeler, {what}: micro-F1 {:.3}, macro-F1 {:.3}",
        f.micro, f.macro_
    );
    assert!(f.micro >= micro, "micro-F1 {:.3} below {micro}", f.micro);
    assert!(
        f.macro_ >= macro_,
        "macro-F1 {:.3} below {macro_}",
        f.macro_
    );
    for (k, lab) in onto.labels().iter().enumerate() {
        let col = |m: &[Vec<bool>]| m.iter().map(|r| vec![r[k]]).collect::<Vec<_>>();
        let fk = f1_scores(&col(&truth), &col(&pred)).micro;
        assert!(fk >= label, "{}: F1 {fk:.3} below {label}", lab.id);
    }
}

/// The errors the issue reports from the previous matcher, and its examples.
#[test]
#[ignore = "needs assets: scripts/fetch-assets.sh"]
fn issue_examples_are_read_as_the_guidelines_say() {
    labeler();
    let cases: &[(&str, &[&str])] = &[
        (
            "Turn right at the roundabout (third exit).",
            &["turn_right", "junction_ahead"],
        ),
        (
            "Road is dry, weather not a factor. Brake for the queue ahead.",
            &["brake"],
        ),
        ("Stop at the red light.", &["stop", "traffic_light_ahead"]),
        (
            "Slow down, roundabout ahead, be ready to stop.",
            &["brake", "junction_ahead"],
        ),
        (
            "There is no traffic light, but an intersection is ahead.",
            &["junction_ahead"],
        ),
        (
            "There is no need to brake; continue driving normally.",
            &["drive_as_normal"],
        ),
        ("You don't have to stop here.", &[]),
        (
            "Don't forget to check the blind spot.",
            &["check_blind_spot"],
        ),
        (
            "Avoid following the truck too closely.",
            &["maintain_safe_distance"],
        ),
        (
            "Pedestrians are crossing; stop and let them cross.",
            &["stop"],
        ),
        (
            "Give way to pedestrians at the zebra.",
            &["pedestrian_crossing_ahead", "yield_to_traffic"],
        ),
        ("Keep left and continue.", &["drive_as_normal"]),
    ];
    assert_cases(cases);
}

#[test]
#[ignore = "needs assets: scripts/fetch-assets.sh"]
fn evidence_names_the_clause_and_the_discounted_mentions() {
    let l = labeler();
    let out = l
        .label_blocking("No need to stop, just slow down. Be ready to turn left at the junction.")
        .unwrap();
    assert_eq!(out.labels, vec!["brake", "junction_ahead"]);
    let ev = |id: &str| out.evidence.iter().find(|e| e.label == id).cloned();
    let brake = ev("brake").expect("evidence for brake");
    assert!(
        brake.accepted && brake.source == EvidenceSource::Rule,
        "{brake:?}"
    );
    assert_eq!(brake.clause, "No need to stop, just slow down.");
    let stop = ev("stop").expect("the negated stop is shown");
    assert!(!stop.accepted && stop.negated && !stop.hedged, "{stop:?}");
    let left = ev("turn_left").expect("the hedged turn is shown");
    assert!(!left.accepted && left.hedged, "{left:?}");
    // Every label that is on has accepted evidence.
    for id in &out.labels {
        assert!(
            out.evidence.iter().any(|e| &e.label == id && e.accepted),
            "{id}: {out:?}"
        );
    }
}

#[test]
#[ignore = "needs assets: scripts/fetch-assets.sh"]
fn outputs_cover_the_ontology_in_order() {
    let l = labeler();
    let out = l
        .label_blocking("Turn left at the junction and yield to oncoming traffic.")
        .unwrap();
    let ids: Vec<&str> = out.scores.iter().map(|s| s.id.as_str()).collect();
    assert_eq!(ids, Ontology::default_driving().ids().collect::<Vec<_>>());
    assert_eq!(
        out.labels,
        vec!["turn_left", "junction_ahead", "yield_to_traffic"]
    );
    assert!(l.label_blocking("").unwrap().labels.is_empty());
    assert!(l.label_blocking("   \n\n").unwrap().labels.is_empty());
}

/// Counts encoder calls, to check that a round costs one.
struct Counting {
    inner: Arc<dyn SentenceEncoder>,
    calls: Mutex<Vec<usize>>,
}

impl SentenceEncoder for Counting {
    fn engine(&self) -> &str {
        "counting"
    }
    fn dim(&self) -> usize {
        self.inner.dim()
    }
    fn encode(&self, texts: &[&str]) -> Result<Vec<Vec<f32>>, vlmfuse_models::ModelError> {
        self.calls.lock().unwrap().push(texts.len());
        self.inner.encode(texts)
    }
}

#[tokio::test]
#[ignore = "needs assets: scripts/fetch-assets.sh"]
async fn async_trait_path_matches_blocking() {
    let l = labeler();
    let text = "Reduce speed on the icy road, and keep a safe gap to the bus.";
    let a = Labeler::label(&pooled(l), text).await.unwrap();
    assert_eq!(a, l.label_blocking(text).unwrap());
    assert!(
        a.labels.contains(&"maintain_safe_distance".to_string()),
        "{a:?}"
    );
}

#[tokio::test]
#[ignore = "needs assets: scripts/fetch-assets.sh"]
async fn a_round_is_one_encoder_call_and_matches_single_labels() {
    let a = common::assets();
    let enc = Arc::new(Counting {
        inner: Arc::new(vlmfuse_labeler::CandleEncoder::load(&a.minilm_dir).unwrap()),
        calls: Mutex::new(Vec::new()),
    });
    let l = Arc::new(
        EmbeddingLabeler::with_encoder(
            Ontology::default_driving(),
            EmbeddingConfig::new(&a.minilm_dir),
            enc.clone(),
        )
        .unwrap(),
    );
    enc.calls.lock().unwrap().clear();
    let texts = [
        "1. Scene: a busy road.\n2. Manoeuvre: hop over into the next lane and get up to speed.\n3. Rationale: our lane ends.",
        "Keep a safe gap to the bus and carry on.",
        "Red light ahead. Stop at the line.",
    ];
    let batch = l.label_batch_blocking(&texts).unwrap();
    assert_eq!(
        enc.calls.lock().unwrap().len(),
        1,
        "one encoder pass per round"
    );
    for (t, b) in texts.iter().zip(&batch) {
        assert_eq!(&l.label_blocking(t).unwrap(), b);
    }
    // Through the service's adapter: still one encoder pass for the round.
    let pool = pooled(&l);
    enc.calls.lock().unwrap().clear();
    let via_trait = Labeler::label_batch(&pool, &texts).await.unwrap();
    assert_eq!(via_trait, batch);
    assert_eq!(
        enc.calls.lock().unwrap().len(),
        1,
        "one encoder pass per round through the pool"
    );
    assert_eq!(Labeler::label(&pool, texts[2]).await.unwrap(), batch[2]);
    assert_eq!(batch[2].labels, vec!["stop", "traffic_light_ahead"]);
}

#[test]
#[ignore = "needs assets: scripts/fetch-assets.sh"]
fn custom_ontology_works_from_names_and_descriptions() {
    let a = common::assets();
    let onto = Ontology::new(vec![
        Label::new("cyclist", "cyclist", Some("a cyclist riding on the road")),
        Label::new(
            "roadworks",
            "roadworks",
            Some("road works and construction cones"),
        ),
        Label::new("animal", "animal", Some("an animal on the road")),
    ])
    .unwrap();
    // Names and descriptions alone are weak prototypes; configured paraphrases extend them.
    let mut cfg = EmbeddingConfig::new(&a.minilm_dir);
    cfg.prototypes.insert(
        "roadworks".into(),
        vec![
            "traffic cones block the lane".into(),
            "construction workers on the road".into(),
        ],
    );
    let l = EmbeddingLabeler::load(onto, cfg).unwrap();
    let out = l
        .label_blocking("A cyclist is riding on the road ahead of us.")
        .unwrap();
    assert_eq!(out.labels, vec!["cyclist"], "{out:?}");
    let out = l
        .label_blocking(
            "Orange cones and construction workers block the lane. There is no cyclist.",
        )
        .unwrap();
    assert_eq!(out.labels, vec!["roadworks"], "{out:?}");
    assert!(out
        .evidence
        .iter()
        .all(|e| e.source == EvidenceSource::Embedding));
    // Unknown label ids in the config are rejected rather than ignored.
    let mut cfg = EmbeddingConfig::new(&a.minilm_dir);
    cfg.label_thresholds.insert("nope".into(), 0.5);
    let onto = Ontology::new(vec![Label::new("x", "x", None)]).unwrap();
    assert!(EmbeddingLabeler::load(onto.clone(), cfg).is_err());
    let mut cfg = EmbeddingConfig::new(&a.minilm_dir);
    cfg.threshold = 1.5;
    assert!(EmbeddingLabeler::load(onto, cfg).is_err());
}

/// Floors on the held-out test split. Measured micro-F1 and macro-F1 are in README (release
/// build, `examples/labeler_eval.rs`); the floors are the issue's targets.
#[test]
#[ignore = "needs assets: scripts/fetch-assets.sh"]
fn test_split_meets_the_targets() {
    assert_floors(
        &default_dataset_path(),
        "test split",
        3,
        250,
        (0.85, 0.80, 0.70),
    );
}

/// The kinds of miss the labeler-round-two issue reports in other answer styles (its
/// paraphrases, and the guideline examples added for them).
#[test]
#[ignore = "needs assets: scripts/fetch-assets.sh"]
fn other_styles_kinds_are_read_as_the_guidelines_say() {
    labeler();
    let cases: &[(&str, &[&str])] = &[
        // A negated action next to an affirmed scene keeps the scene and the carry-on.
        (
            "not stopping here, light is green at the intersection, go.",
            &["traffic_light_ahead", "junction_ahead", "drive_as_normal"],
        ),
        // Weather that motivates a change, stated compactly.
        ("It's icy, keep it slow.", &["adjust_speed_due_to_weather"]),
        ("Hold back, the road is wet.", &["adjust_speed_due_to_weather"]),
        ("Road's icy - go easy.", &["adjust_speed_due_to_weather"]),
        ("Wet road. Keep your speed steady.", &["drive_as_normal"]),
        // Implicit yielding.
        ("Turn once the oncoming van has passed.", &["yield_to_traffic"]),
        (
            "Hold at the give way line until the tractor has cleared.",
            &["stop", "yield_to_traffic"],
        ),
        (
            "Pull over to the left for the fire engine behind us.",
            &["stop", "yield_to_traffic"],
        ),
        (
            "Give the bus room to pull out from the stop, then continue.",
            &["yield_to_traffic"],
        ),
        (
            "Fog is rolling in; ease back on the speed.",
            &["brake", "adjust_speed_due_to_weather"],
        ),
        ("Snow is settling, go gently.", &["adjust_speed_due_to_weather"]),
        (
            "1) Check mirrors\n2) Signal left\n3) Turn left into Park Road",
            &["turn_left", "junction_ahead", "check_blind_spot"],
        ),
        // Soft but real advice; true hedges stay hedges.
        ("You could speed up a little.", &["accelerate"]),
        ("Maybe you could slow down.", &[]),
        ("You could brake a little earlier if it gets busy.", &[]),
        ("No harm in easing off a touch for the cyclist.", &["brake"]),
        // A list's last item.
        (
            "- Slow down for the junction.\n- Keep a safe gap.\n- Watch for cyclists on the inside.",
            &[
                "brake",
                "junction_ahead",
                "maintain_safe_distance",
                "check_blind_spot",
            ],
        ),
        // Captions: driving on is drive_as_normal; a hazard or a parked car is not.
        (
            "Dashcam: driving along a quiet two-lane road in daylight, light traffic.",
            &["drive_as_normal"],
        ),
        ("A child runs into the road just ahead of the car.", &[]),
        ("The ego car is parked outside a shop.", &[]),
        // Planner abbreviations, key/value forms, typos that are words.
        (
            "Never overtake at this jct; go straight through.",
            &["junction_ahead", "drive_as_normal"],
        ),
        (
            "situation: bus lane ends\nblind_spot: check\naction: move into the left lane",
            &["merge", "check_blind_spot"],
        ),
        (
            "its snowing hard, make the car slower and keep more distnace from the bus",
            &["brake", "maintain_safe_distance", "adjust_speed_due_to_weather"],
        ),
    ];
    assert_cases(cases);
}

/// Floors on the held-out part of the second set (other styles): the labeler-round-two issue's
/// targets, micro-F1 >= 0.93, macro-F1 >= 0.90, no label below 0.75.
#[test]
#[ignore = "needs assets: scripts/fetch-assets.sh"]
fn other_styles_test_split_meets_the_targets() {
    assert_floors(
        &styles_dataset_path(),
        "other styles test split",
        5,
        150,
        (0.93, 0.90, 0.75),
    );
}

/// The labeler as the service runs it: behind its worker thread.
fn pooled(l: &Arc<EmbeddingLabeler>) -> BackendPool<EmbeddingLabeler> {
    BackendPool::new(l.name(), l.clone(), PoolConfig::default()).unwrap()
}
