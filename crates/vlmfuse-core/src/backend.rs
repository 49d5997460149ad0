//! One adapter that turns a blocking backend (a model whose calls occupy the calling thread for
//! milliseconds to minutes) into an async one, after text-embeddings-inference's
//! `BackendThread`.
//!
//! Why: each local backend used to call `spawn_blocking` itself, and the in-process VLM took a
//! `Mutex` inside the blocking thread, so N queued clips held N threads of tokio's blocking pool
//! while they waited for the one model. Here a backend gets its own small pool of dedicated
//! threads and a bounded queue in front of them:
//!
//! * waiting work is a queue entry, not a parked thread;
//! * a full queue refuses at once ([`BackendError::QueueFull`]) instead of growing without bound;
//! * dropping the future of a call (a request timeout, a client gone, a reporter's round timeout)
//!   cancels it: queued work is skipped, and running work sees its cancel flag set so that a
//!   cooperative backend (token-by-token generation) stops at its next step;
//! * an optional per-call timeout covers the wait in the queue and the work;
//! * a panic in the backend is an error for that call; the worker lives on.

use std::panic::AssertUnwindSafe;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;
use tokio::sync::{mpsc, oneshot};

/// How a backend's pool is sized.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PoolConfig {
    /// Dedicated worker threads, each running one call at a time. One is right for a model that
    /// already uses every core per call (candle's matmuls do), or that has one device.
    pub threads: usize,
    /// Calls waiting for a worker before new ones are refused.
    pub queue: usize,
    /// Longest a call may take, queue wait included; `None`: the caller's own timeout decides.
    pub timeout: Option<Duration>,
}

impl Default for PoolConfig {
    fn default() -> Self {
        Self {
            threads: 1,
            queue: 64,
            timeout: None,
        }
    }
}

/// Why a call produced no result.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum BackendError {
    #[error("{backend}: {capacity} calls are already queued; retry later")]
    QueueFull { backend: String, capacity: usize },
    #[error("{backend}: timed out after {:.3}s", .after.as_secs_f64())]
    TimedOut { backend: String, after: Duration },
    #[error("{backend}: the worker has stopped")]
    Stopped { backend: String },
    #[error("{backend} panicked: {message}")]
    Panicked { backend: String, message: String },
}

type Work<B> = Box<dyn FnOnce(&B, &AtomicBool) + Send>;

struct Job<B: ?Sized> {
    cancel: Arc<AtomicBool>,
    work: Work<B>,
}

/// Sets the flag when a call's future is dropped (timeout, cancellation), so that queued work is
/// skipped and running work can stop early.
struct CancelOnDrop(Arc<AtomicBool>);

impl Drop for CancelOnDrop {
    fn drop(&mut self) {
        self.0.store(true, Ordering::Relaxed);
    }
}

/// A blocking backend behind its own worker threads and a bounded queue.
pub struct BackendPool<B: ?Sized + Send + Sync + 'static> {
    name: String,
    backend: Arc<B>,
    tx: mpsc::Sender<Job<B>>,
    cfg: PoolConfig,
}

impl<B: ?Sized + Send + Sync + 'static> BackendPool<B> {
    /// Starts `cfg.threads` workers named after `name` (as logs and `/readyz` show it).
    pub fn new(name: impl Into<String>, backend: Arc<B>, cfg: PoolConfig) -> std::io::Result<Self> {
        let name = name.into();
        let (tx, rx) = mpsc::channel::<Job<B>>(cfg.queue.max(1));
        let rx = Arc::new(Mutex::new(rx));
        for i in 0..cfg.threads.max(1) {
            let (rx, backend) = (rx.clone(), backend.clone());
            std::thread::Builder::new()
                .name(format!("vlmfuse-{name}-{i}"))
                .spawn(move || worker(&rx, &*backend))?;
        }
        Ok(Self {
            name,
            backend,
            tx,
            cfg,
        })
    }

    pub fn name(&self) -> &str {
        &self.name
    }

    /// The backend itself, for cheap synchronous reads (its name, its dimension) and tests.
    pub fn backend(&self) -> &Arc<B> {
        &self.backend
    }

    pub fn config(&self) -> &PoolConfig {
        &self.cfg
    }

    /// Runs `work` on a worker. `work` gets the backend and the call's cancel flag, which is set
    /// once nobody waits for the result any more.
    pub async fn call<R, F>(&self, work: F) -> Result<R, BackendError>
    where
        F: FnOnce(&B, &AtomicBool) -> R + Send + 'static,
        R: Send + 'static,
    {
        let cancel = Arc::new(AtomicBool::new(false));
        let _guard = CancelOnDrop(cancel.clone());
        let (reply, rx) = oneshot::channel();
        let job = Job {
            cancel,
            work: Box::new(move |b: &B, c: &AtomicBool| {
                let res = std::panic::catch_unwind(AssertUnwindSafe(|| work(b, c)));
                let _ = reply.send(res.map_err(|p| panic_message(p.as_ref())));
            }),
        };
        self.tx.try_send(job).map_err(|e| match e {
            mpsc::error::TrySendError::Full(_) => BackendError::QueueFull {
                backend: self.name.clone(),
                capacity: self.cfg.queue,
            },
            mpsc::error::TrySendError::Closed(_) => BackendError::Stopped {
                backend: self.name.clone(),
            },
        })?;
        let result = async {
            match rx.await {
                Err(_) => Err(BackendError::Stopped {
                    backend: self.name.clone(),
                }),
                Ok(Err(message)) => Err(BackendError::Panicked {
                    backend: self.name.clone(),
                    message,
                }),
                Ok(Ok(r)) => Ok(r),
            }
        };
        match self.cfg.timeout {
            None => result.await,
            Some(after) => {
                tokio::time::timeout(after, result)
                    .await
                    .map_err(|_| BackendError::TimedOut {
                        backend: self.name.clone(),
                        after,
                    })?
            }
        }
    }
}

fn worker<B: ?Sized>(rx: &Mutex<mpsc::Receiver<Job<B>>>, backend: &B) {
    loop {
        // The lock is held while waiting, so idle workers queue on the mutex, not on the channel.
        let job = match rx.lock() {
            Ok(mut rx) => rx.blocking_recv(),
            Err(_) => None,
        };
        let Some(job) = job else { return };
        if job.cancel.load(Ordering::Relaxed) {
            tracing::debug!("skipping a call whose caller has gone");
            continue;
        }
        (job.work)(backend, &job.cancel);
    }
}

/// The text of a panic payload.
pub fn panic_message(p: &(dyn std::any::Any + Send)) -> String {
    if let Some(s) = p.downcast_ref::<&str>() {
        s.to_string()
    } else if let Some(s) = p.downcast_ref::<String>() {
        s.clone()
    } else {
        "non-string panic payload".into()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::atomic::AtomicUsize;
    use std::time::Instant;

    /// Counts the calls that really ran.
    #[derive(Default)]
    struct Counter(AtomicUsize);

    fn pool(cfg: PoolConfig) -> BackendPool<Counter> {
        BackendPool::new("test", Arc::new(Counter::default()), cfg).unwrap()
    }

    #[tokio::test]
    async fn calls_run_on_the_workers_and_return() {
        let p = pool(PoolConfig::default());
        let name = p
            .call(|c, _| {
                c.0.fetch_add(1, Ordering::SeqCst);
                std::thread::current().name().unwrap().to_string()
            })
            .await
            .unwrap();
        assert_eq!(name, "vlmfuse-test-0");
        assert_eq!(p.backend().0.load(Ordering::SeqCst), 1);
    }

    #[tokio::test]
    async fn a_full_queue_refuses_at_once() {
        let p = Arc::new(pool(PoolConfig {
            threads: 1,
            queue: 1,
            timeout: None,
        }));
        // One running, one queued: the third is refused.
        let slow = |p: Arc<BackendPool<Counter>>| {
            tokio::spawn(async move {
                p.call(|_, _| std::thread::sleep(Duration::from_millis(300)))
                    .await
            })
        };
        let a = slow(p.clone());
        tokio::time::sleep(Duration::from_millis(50)).await;
        let b = slow(p.clone());
        tokio::time::sleep(Duration::from_millis(50)).await;
        let t0 = Instant::now();
        let e = p.call(|_, _| ()).await.unwrap_err();
        assert!(
            matches!(e, BackendError::QueueFull { capacity: 1, .. }),
            "{e}"
        );
        assert!(t0.elapsed() < Duration::from_millis(100));
        assert!(a.await.unwrap().is_ok() && b.await.unwrap().is_ok());
    }

    #[tokio::test]
    async fn a_timed_out_call_is_skipped_when_queued_and_cancelled_when_running() {
        let p = Arc::new(pool(PoolConfig {
            threads: 1,
            queue: 8,
            timeout: Some(Duration::from_millis(100)),
        }));
        let saw_cancel = Arc::new(AtomicBool::new(false));
        let seen = saw_cancel.clone();
        // Runs until cancelled (or 5 s), polling its flag like a token loop.
        let running = p.call(move |c, cancel| {
            let t0 = Instant::now();
            while !cancel.load(Ordering::Relaxed) && t0.elapsed() < Duration::from_secs(5) {
                std::thread::sleep(Duration::from_millis(5));
            }
            seen.store(cancel.load(Ordering::Relaxed), Ordering::SeqCst);
            c.0.fetch_add(1, Ordering::SeqCst);
        });
        let queued = p.call(|c, _| {
            c.0.fetch_add(100, Ordering::SeqCst);
        });
        let (a, b) = tokio::join!(running, queued);
        assert!(matches!(a, Err(BackendError::TimedOut { .. })), "{a:?}");
        assert!(matches!(b, Err(BackendError::TimedOut { .. })), "{b:?}");
        // The worker is free again soon, and the queued call never ran.
        let n = p.call(|c, _| c.0.load(Ordering::SeqCst));
        let n = tokio::time::timeout(Duration::from_secs(2), n).await;
        assert_eq!(n.unwrap().unwrap(), 1);
        assert!(
            saw_cancel.load(Ordering::SeqCst),
            "the running call saw its cancel flag"
        );
    }

    #[tokio::test]
    async fn a_panic_is_an_error_and_the_worker_survives() {
        let p = pool(PoolConfig::default());
        let e = p
            .call(|_, _| -> () { panic!("model bug") })
            .await
            .unwrap_err();
        assert!(
            matches!(&e, BackendError::Panicked { message, .. } if message == "model bug"),
            "{e}"
        );
        assert_eq!(p.call(|_, _| 7).await.unwrap(), 7);
    }
}
