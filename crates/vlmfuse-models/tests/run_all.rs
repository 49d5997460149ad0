//! `run_all` and `run_all_batch`: concurrency, per-reporter timeouts, and failure isolation.

use std::sync::Arc;
use std::time::{Duration, Instant};

use futures::future::BoxFuture;
use vlmfuse_core::chat::ChatError;
use vlmfuse_models::{
    run_all, run_all_batch, ClipInput, ClipMeta, ModelError, Reporter, ReporterFailure,
    ReporterOutput, RoundReporter,
};

/// Every reporter under the same round timeout.
fn timed(reporters: Vec<Arc<dyn Reporter>>, timeout: Duration) -> Vec<RoundReporter> {
    reporters
        .into_iter()
        .map(|r| RoundReporter::new(r, timeout))
        .collect()
}

enum Behaviour {
    Answer(Duration),
    Fail,
    Panic,
}

struct Fake(&'static str, Behaviour);

impl Reporter for Fake {
    fn name(&self) -> &str {
        self.0
    }
    fn run<'a>(&'a self, clip: &'a ClipInput) -> BoxFuture<'a, Result<ReporterOutput, ModelError>> {
        Box::pin(async move {
            match self.1 {
                Behaviour::Answer(d) => {
                    tokio::time::sleep(d).await;
                    Ok(ReporterOutput {
                        text: format!("{} saw {} frames", self.0, clip.frames.len()),
                        latency_ms: d.as_secs_f64() * 1e3,
                        model: self.0.into(),
                    })
                }
                Behaviour::Fail => Err(ModelError::Chat(ChatError::Remote {
                    endpoint: "http://x".into(),
                    status: Some(502),
                    attempts: 1,
                    message: "bad gateway".into(),
                })),
                Behaviour::Panic => panic!("reporter bug"),
            }
        })
    }
}

#[tokio::test]
async fn slow_and_failing_reporters_do_not_sink_the_round() {
    let reporters: Vec<Arc<dyn Reporter>> = vec![
        Arc::new(Fake("fast", Behaviour::Answer(Duration::from_millis(20)))),
        Arc::new(Fake("slow", Behaviour::Answer(Duration::from_secs(30)))),
        Arc::new(Fake("broken", Behaviour::Fail)),
        Arc::new(Fake(
            "medium",
            Behaviour::Answer(Duration::from_millis(250)),
        )),
    ];
    let clip = ClipInput {
        path: "/nonexistent.mp4".into(),
        frames: Vec::new().into(),
        meta: ClipMeta::default(),
    };
    let timeout = Duration::from_millis(400);
    let t0 = Instant::now();
    let res = run_all(&timed(reporters, timeout), &clip).await;
    let el = t0.elapsed();
    // Concurrent: about one timeout, not 20 + 30000 + 250 ms, and not 400 + 250 either.
    assert!(el >= timeout, "{el:?}");
    assert!(
        el < Duration::from_millis(600),
        "not run concurrently: {el:?}"
    );

    let names: Vec<&str> = res.iter().map(|(n, _)| n.as_str()).collect();
    assert_eq!(names, ["fast", "slow", "broken", "medium"]);
    assert_eq!(res[0].1.as_ref().unwrap().text, "fast saw 0 frames");
    assert!(matches!(res[1].1, Err(ReporterFailure::TimedOut(d)) if d == timeout));
    let broken = res[2].1.as_ref().unwrap_err();
    assert_eq!(broken.kind(), "remote");
    assert!(broken.to_string().contains("502"), "{broken}");
    assert!(res[3].1.is_ok());
}

/// Separate from the timing test: printing a panic's backtrace alone can take longer than the
/// timeout in a debug build.
#[tokio::test]
async fn a_panicking_reporter_is_reported_not_propagated() {
    let reporters: Vec<Arc<dyn Reporter>> = vec![
        Arc::new(Fake("buggy", Behaviour::Panic)),
        Arc::new(Fake("fine", Behaviour::Answer(Duration::from_millis(1)))),
    ];
    let clip = ClipInput {
        path: "/x.mp4".into(),
        frames: Vec::new().into(),
        meta: ClipMeta::default(),
    };
    let res = run_all(&timed(reporters, Duration::from_secs(5)), &clip).await;
    let buggy = res[0].1.as_ref().unwrap_err();
    assert_eq!(buggy.kind(), "panic");
    assert!(buggy.to_string().contains("reporter bug"), "{buggy}");
    assert!(res[1].1.is_ok());
}

#[tokio::test]
async fn no_reporters_is_an_empty_round() {
    let clip = ClipInput {
        path: "/x.mp4".into(),
        frames: Vec::new().into(),
        meta: ClipMeta::default(),
    };
    assert!(run_all(&[], &clip).await.is_empty());
}

fn clip_with(n: usize) -> ClipInput {
    ClipInput {
        path: "/x.mp4".into(),
        frames: (0..n)
            .map(|_| vlmfuse_models::Frame {
                width: 1,
                height: 1,
                rgb: vec![0; 3],
                pts_s: 0.0,
            })
            .collect::<Vec<_>>()
            .into(),
        meta: ClipMeta::default(),
    }
}

/// A request's clips: each reporter's outcomes come back per clip, in clip and reporter order;
/// the batch gets the round timeout once per clip (three 150 ms clips run concurrently by the
/// default `run_batch` fit in 3 x 100 ms), and a failing or slow reporter fails every clip
/// of its batch alone.
#[tokio::test]
async fn run_all_batch_answers_per_clip() {
    let reporters: Vec<Arc<dyn Reporter>> = vec![
        Arc::new(Fake("a", Behaviour::Answer(Duration::from_millis(150)))),
        Arc::new(Fake("broken", Behaviour::Fail)),
        Arc::new(Fake("slow", Behaviour::Answer(Duration::from_secs(30)))),
    ];
    let clips = [clip_with(1), clip_with(2), clip_with(3)];
    let t0 = Instant::now();
    let res = run_all_batch(&timed(reporters, Duration::from_millis(100)), &clips).await;
    assert!(t0.elapsed() < Duration::from_secs(2), "{:?}", t0.elapsed());
    assert_eq!(res.len(), 3);
    for (i, per) in res.iter().enumerate() {
        let names: Vec<&str> = per.iter().map(|(n, _)| n.as_str()).collect();
        assert_eq!(names, ["a", "broken", "slow"]);
        assert_eq!(
            per[0].1.as_ref().unwrap().text,
            format!("a saw {} frames", i + 1)
        );
        assert_eq!(per[1].1.as_ref().unwrap_err().kind(), "remote");
        assert!(
            matches!(per[2].1, Err(ReporterFailure::TimedOut(d)) if d == Duration::from_millis(300))
        );
    }
    assert!(run_all_batch(&[], &clips)
        .await
        .iter()
        .all(|p| p.is_empty()));
}
