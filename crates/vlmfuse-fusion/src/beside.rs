//! A second thread that runs one job beside the caller's own work, for
//! [`crate::Engine::observe_ahead`]: an import searches the next round's neighbours there while
//! the engine runs this round's EM chunk.
//!
//! Why not a thread per job, or a pool's `join`: the two halves take 0.1–0.3 ms each, and on
//! this project's machines (virtual, two cores) starting a thread, or waking a sleeping one,
//! costs 40–90 µs, which ate the whole gain (measured: the parallel version was no faster than
//! the serial one). This thread stays awake between jobs by yielding its core (other runnable
//! threads, an import's reader and writer, get it first) and sleeps only after a quiet spell.
//! A job it has not started when the caller's own half ends is taken back and run by the
//! caller, so a late or busy helper never makes a step slower than running both halves in
//! turn. Which thread runs a job never changes its result.

use std::any::Any;
use std::sync::atomic::{AtomicU8, Ordering};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

type Job = Box<dyn FnOnce() + Send>;

const IDLE: u8 = 0;
const POSTED: u8 = 1;
const TAKEN: u8 = 2;
const DONE: u8 = 3;
const STOP: u8 = 4;

/// How long the helper keeps its core (yielding) after a job before it sleeps.
const AWAKE: Duration = Duration::from_millis(5);

struct Shared {
    state: AtomicU8,
    job: Mutex<Option<Job>>,
}

/// The helper thread (see the module doc). One job at a time: concurrent callers of
/// [`Beside::run`] take turns.
pub struct Beside {
    shared: Arc<Shared>,
    worker: Option<JoinHandle<()>>,
    turn: Mutex<()>,
}

impl std::fmt::Debug for Beside {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Beside")
            .field("running", &self.worker.is_some())
            .finish()
    }
}

impl Default for Beside {
    fn default() -> Self {
        Self::new()
    }
}

fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    // A job's panic is caught before it could poison the lock; recover anyway.
    m.lock().unwrap_or_else(|e| e.into_inner())
}

impl Beside {
    /// Starts the helper. Without a thread (the system refused one), every job runs on the
    /// caller's thread after its own half.
    pub fn new() -> Self {
        let shared = Arc::new(Shared {
            state: AtomicU8::new(IDLE),
            job: Mutex::new(None),
        });
        let s = Arc::clone(&shared);
        let worker = std::thread::Builder::new()
            .name("vlmfuse-beside".into())
            .spawn(move || {
                let mut last = Instant::now();
                loop {
                    match s.state.load(Ordering::Acquire) {
                        STOP => return,
                        POSTED => {
                            if s.state
                                .compare_exchange(
                                    POSTED,
                                    TAKEN,
                                    Ordering::AcqRel,
                                    Ordering::Acquire,
                                )
                                .is_ok()
                            {
                                if let Some(job) = lock(&s.job).take() {
                                    job();
                                }
                                s.state.store(DONE, Ordering::Release);
                            }
                            last = Instant::now();
                        }
                        _ if last.elapsed() < AWAKE => std::thread::yield_now(),
                        _ => std::thread::park_timeout(Duration::from_millis(50)),
                    }
                }
            })
            .ok();
        Self {
            shared,
            worker,
            turn: Mutex::new(()),
        }
    }

    /// Runs `job` on the helper while `here` runs on this thread, and returns `job`'s value
    /// (its panic, if it panicked, resumes here). `job` runs here, after `here`, when the
    /// helper has not started it by then.
    pub fn run<R: Send + 'static>(
        &self,
        job: impl FnOnce() -> R + Send + 'static,
        here: impl FnOnce(),
    ) -> R {
        let Some(worker) = &self.worker else {
            here();
            return job();
        };
        let _turn = lock(&self.turn);
        type Out<R> = Arc<Mutex<Option<Result<R, Box<dyn Any + Send>>>>>;
        let out: Out<R> = Arc::new(Mutex::new(None));
        let o = Arc::clone(&out);
        let boxed: Job = Box::new(move || {
            let r = std::panic::catch_unwind(std::panic::AssertUnwindSafe(job));
            *lock(&o) = Some(r);
        });
        let s = &self.shared;
        *lock(&s.job) = Some(boxed);
        s.state.store(POSTED, Ordering::Release);
        worker.thread().unpark();
        here();
        if s.state
            .compare_exchange(POSTED, IDLE, Ordering::AcqRel, Ordering::Acquire)
            .is_ok()
        {
            // Not started: run it here.
            if let Some(job) = lock(&s.job).take() {
                job();
            }
        } else {
            while s.state.load(Ordering::Acquire) != DONE {
                std::hint::spin_loop();
            }
            s.state.store(IDLE, Ordering::Release);
        }
        let r = lock(&out).take();
        match r {
            Some(Ok(v)) => v,
            Some(Err(panic)) => std::panic::resume_unwind(panic),
            None => unreachable!("a finished job leaves its value"),
        }
    }
}

impl Drop for Beside {
    fn drop(&mut self) {
        self.shared.state.store(STOP, Ordering::Release);
        if let Some(w) = self.worker.take() {
            w.thread().unpark();
            let _ = w.join();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn jobs_run_beside_and_return_their_values() {
        let b = Beside::new();
        for i in 0..2000u64 {
            let mut here = 0;
            let v = b.run(move || i * 3, || here = i + 1);
            assert_eq!((v, here), (i * 3, i + 1));
        }
        // The job runs on the helper while the caller's half runs: it sees the caller's
        // half still going (the flag is set only at its end), on the helper's thread.
        let flag = Arc::new(std::sync::atomic::AtomicBool::new(false));
        let f = Arc::clone(&flag);
        let (name, early) = b.run(
            move || {
                let early = !f.load(Ordering::Acquire);
                (std::thread::current().name().map(String::from), early)
            },
            || {
                std::thread::sleep(Duration::from_millis(250));
                flag.store(true, Ordering::Release);
            },
        );
        assert_eq!(name.as_deref(), Some("vlmfuse-beside"));
        assert!(early, "the job ran after the caller's half");
    }

    #[test]
    fn a_panicking_job_panics_the_caller_and_the_helper_goes_on() {
        let b = Beside::new();
        let r = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
            b.run(|| -> u32 { panic!("job failed") }, || {})
        }));
        assert!(r.is_err());
        assert_eq!(b.run(|| 7, || {}), 7);
    }
}
