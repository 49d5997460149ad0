//! Prometheus metrics, one recorder per service instance.
//!
//! Why not the usual process-wide recorder alone: the service tests run several services in one
//! process (in-process `app().oneshot()`), and gauges such as `vlmfuse_labelled_rounds` would mix
//! between them. So every instance owns a recorder, and the code that serves it runs inside it:
//! request futures through [`Metrics::instrument`] (the outermost layer of the router), the
//! writer thread and blocking work through [`Metrics::scope`]. `serve::run` also installs the
//! recorder process-wide, so that in the binary a metric emitted anywhere is kept.

use metrics::Recorder;
use metrics_exporter_prometheus::{PrometheusBuilder, PrometheusHandle, PrometheusRecorder};
use std::future::Future;
use std::pin::Pin;
use std::sync::Arc;
use std::task::{Context, Poll};

#[derive(Clone)]
pub struct Metrics {
    recorder: Arc<PrometheusRecorder>,
    handle: PrometheusHandle,
}

impl Metrics {
    /// A fresh recorder with the service's buckets and descriptions.
    pub fn new() -> anyhow::Result<Self> {
        const BUCKETS: [f64; 14] = [
            0.0001, 0.00025, 0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0,
            5.0,
        ];
        let recorder = Arc::new(
            PrometheusBuilder::new()
                .set_buckets(&BUCKETS)?
                .build_recorder(),
        );
        let handle = recorder.handle();
        let m = Self { recorder, handle };
        m.scope(describe);
        Ok(m)
    }

    /// Makes this recorder the process-wide one (the binary; at most once per process).
    pub fn install_global(&self) -> anyhow::Result<()> {
        metrics::set_global_recorder(self.recorder.clone())
            .map_err(|e| anyhow::anyhow!("metrics recorder: {e}"))
    }

    /// Prometheus text.
    pub fn render(&self) -> String {
        self.handle.render()
    }

    /// Runs `f` with this recorder in force on the current thread.
    pub fn scope<T>(&self, f: impl FnOnce() -> T) -> T {
        metrics::with_local_recorder(&*self.recorder as &dyn Recorder, f)
    }

    /// A future that polls `fut` with this recorder in force (on whichever thread polls it).
    pub fn instrument<F: Future>(&self, fut: F) -> Instrumented<F> {
        Instrumented {
            fut: Box::pin(fut),
            metrics: self.clone(),
        }
    }
}

pub struct Instrumented<F> {
    fut: Pin<Box<F>>,
    metrics: Metrics,
}

impl<F: Future> Future for Instrumented<F> {
    type Output = F::Output;
    fn poll(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<F::Output> {
        let this = self.get_mut();
        let fut = this.fut.as_mut();
        this.metrics.scope(|| fut.poll(cx))
    }
}

fn describe() {
    use metrics::{describe_counter, describe_gauge, describe_histogram, Unit};
    describe_counter!(
        "vlmfuse_http_requests_total",
        "HTTP requests by route, method and status"
    );
    describe_histogram!(
        "vlmfuse_http_request_duration_seconds",
        Unit::Seconds,
        "HTTP request latency by route"
    );
    describe_histogram!(
        "vlmfuse_fusion_duration_seconds",
        Unit::Seconds,
        "Inference time of one /v1/fuse request (all its rounds)"
    );
    describe_histogram!(
        "vlmfuse_feedback_duration_seconds",
        Unit::Seconds,
        "Feedback time in the writer: credit, commit, apply"
    );
    describe_gauge!("vlmfuse_reputation", "Public reputation w of each reporter");
    describe_gauge!("vlmfuse_labelled_rounds", "Labelled rounds in the bank");
    describe_gauge!("vlmfuse_threshold", "Decision threshold in force");
    describe_counter!(
        "vlmfuse_rejected_requests_total",
        "Requests answered with an error, by kind"
    );
    describe_counter!(
        "vlmfuse_overload_total",
        "Requests refused with 429 at the concurrency limit"
    );
    describe_counter!("vlmfuse_rounds_stored_total", "Rounds fused and committed");
    describe_histogram!(
        "vlmfuse_stage_seconds",
        Unit::Seconds,
        "Time of each /v1/infer stage per clip: upload, decode, embed, reporters, label, fuse"
    );
    describe_counter!(
        "vlmfuse_reporter_failures_total",
        "Reporters left out of a /v1/infer round, by reporter and stage (run, label)"
    );
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Two instances in one process keep their own numbers.
    #[tokio::test]
    async fn instances_do_not_share_metrics() {
        let (a, b) = (Metrics::new().unwrap(), Metrics::new().unwrap());
        a.scope(|| metrics::gauge!("vlmfuse_labelled_rounds").set(3.0));
        b.instrument(async {
            tokio::task::yield_now().await;
            metrics::gauge!("vlmfuse_labelled_rounds").set(5.0);
        })
        .await;
        assert!(
            a.render().contains("vlmfuse_labelled_rounds 3"),
            "{}",
            a.render()
        );
        assert!(
            b.render().contains("vlmfuse_labelled_rounds 5"),
            "{}",
            b.render()
        );
    }
}
