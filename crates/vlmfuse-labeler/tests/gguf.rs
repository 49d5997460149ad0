//! The GGUF labeler with the real gemma-3-270m Q4_K_M: tokenizer round trips, the cached-prefix
//! path against full forward passes, and scoring of a few answers (the full evaluation runs in
//! release in `examples/labeler_eval.rs`).

mod common;

use std::sync::{Arc, OnceLock};
use vlmfuse_labeler::{
    BackendPool, BlockingLabeler, GgufConfig, GgufLabeler, Label, Labeler, Ontology, PoolConfig,
    SpTokenizer,
};

/// One model load for all tests (a load costs about a minute in a debug build). A small custom
/// ontology checks that other label sets work and keeps the full-forward comparison cheap; the
/// default ontology is evaluated in release by `examples/labeler_eval.rs`.
fn small() -> Option<&'static Arc<GgufLabeler>> {
    static L: OnceLock<Option<Arc<GgufLabeler>>> = OnceLock::new();
    L.get_or_init(|| {
        let a = common::assets()?;
        let onto = Ontology::new(vec![
            Label::new(
                "traffic_light_ahead",
                "traffic light ahead",
                Some("a traffic light"),
            ),
            Label::new("merge", "merge", Some("merging or changing lanes")),
            Label::new("cyclist", "cyclist", Some("a cyclist")),
            Label::new("snow", "snow", None),
        ])
        .unwrap();
        Some(Arc::new(
            GgufLabeler::load(onto, GgufConfig::new(&a.gemma_gguf)).expect("load gguf labeler"),
        ))
    })
    .as_ref()
}

#[test]
fn tokenizer_round_trips_and_uses_sentencepiece_pieces() {
    let Some(a) = common::assets() else { return };
    // The tokenizer needs only the GGUF metadata, not the weights.
    let mut f = std::fs::File::open(&a.gemma_gguf).unwrap();
    let ct = candle_core::quantized::gguf_file::Content::read(&mut f).unwrap();
    let tok = SpTokenizer::from_gguf(&ct).unwrap();
    assert_eq!(tok.vocab_size(), 262_144);
    assert_eq!(tok.bos_id(), Some(2));
    for t in [
        "Driving description: The car is slowing down at a zebra crossing.\nAnswer:",
        "Ünïcödé ≠ ascii 😀, numbers 12345",
        "  two  spaces",
    ] {
        assert_eq!(tok.decode(&tok.encode(t)), t);
    }
    let ids = tok.encode("Does the description mention braking? Answer: yes");
    let pieces: Vec<&str> = ids.iter().map(|&i| tok.piece(i).unwrap()).collect();
    assert_eq!(
        pieces,
        [
            "Does",
            "▁the",
            "▁description",
            "▁mention",
            "▁braking",
            "?",
            "▁Answer",
            ":",
            "▁yes"
        ]
    );
}

#[test]
fn cached_prefix_matches_full_forward() {
    let Some(l) = small() else { return };
    let text = "The light ahead is red. A cyclist waits at the line.";
    let cached = l.raw_log_odds(text, true).unwrap();
    let full = l.raw_log_odds(text, false).unwrap();
    assert_eq!(cached.len(), 4);
    // Measured max difference 0.06 (batched vs single-row quantized matmuls round differently);
    // a cache bug such as a masked-out prefix changes the log-odds by whole units.
    let max = cached
        .iter()
        .zip(&full)
        .map(|(a, b)| (a - b).abs())
        .fold(0f32, f32::max);
    assert!(max < 0.25, "cached {cached:?} vs full {full:?}");
}

#[tokio::test]
async fn labels_answers_with_probabilities() {
    let Some(l) = small() else { return };
    let out = Labeler::label(
        &pooled(l),
        "1. Scene: A red traffic light at a busy intersection.\n2. Manoeuvre: Brake and stop at the line.\n3. Rationale: The light is red.",
    )
    .await
    .unwrap();
    assert_eq!(out.scores.len(), 4);
    assert!(out.scores.iter().all(|s| (0.0..=1.0).contains(&s.score)));
    // Weak model, but an explicit, repeated mention must outscore an unrelated label.
    let s = |id| out.score_of(id).unwrap();
    assert!(s("traffic_light_ahead") > s("merge"), "{out:?}");
}

#[test]
fn works_with_a_custom_ontology() {
    let Some(l) = small() else { return };
    let out = l
        .label_blocking("A cyclist is riding next to the car on a sunny day.")
        .unwrap();
    assert_eq!(out.scores.len(), 4);
    assert_eq!(out.scores[2].id, "cyclist");
    assert!(out.scores.iter().all(|s| (0.0..=1.0).contains(&s.score)));
    // No discrimination is asserted here: the 270M base model scored "snow" (0.77) above
    // "cyclist" (0.75) for a sunny cyclist scene; see the crate report.
}

/// The labeler as the service runs it: behind its worker thread.
fn pooled(l: &Arc<GgufLabeler>) -> BackendPool<GgufLabeler> {
    BackendPool::new(l.name(), l.clone(), PoolConfig::default()).unwrap()
}
