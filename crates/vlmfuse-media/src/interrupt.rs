//! A deadline and a cancellation flag that the caller hands to a decode, so that work nobody is
//! waiting for stops.
//!
//! FFmpeg is synchronous: once a server has moved a decode onto a blocking thread, a timed-out
//! or disconnected request cannot take that thread back. The decode therefore polls an
//! [`Interrupt`] itself: FFmpeg's I/O layer asks it before every read (through the format
//! context's interrupt callback, so even a stalled open or `avformat_find_stream_info` stops),
//! and the sampling loop asks it before every packet it hands to the decoder.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use crate::MediaError;

/// A cancellation flag and an optional deadline, shared by the caller and the decode.
///
/// Cloning shares the same flag: keep one clone, pass another to
/// [`crate::sample_frames_with_interrupt`], and [`Interrupt::cancel`] from anywhere (another
/// thread, an async task). Checking costs an atomic load and, with a deadline, a clock read.
#[derive(Debug, Clone, Default)]
pub struct Interrupt {
    inner: Arc<Inner>,
}

#[derive(Debug, Default)]
struct Inner {
    cancelled: AtomicBool,
    deadline: Option<Instant>,
}

impl Interrupt {
    /// Never expires; stops only when cancelled.
    pub fn new() -> Self {
        Self::default()
    }

    /// Stops the decode once `deadline` has passed.
    pub fn with_deadline(deadline: Instant) -> Self {
        Interrupt {
            inner: Arc::new(Inner {
                cancelled: AtomicBool::new(false),
                deadline: Some(deadline),
            }),
        }
    }

    /// Stops the decode `timeout` from now. A timeout too large to represent means no deadline
    /// (rather than a panic on overflow).
    pub fn with_timeout(timeout: Duration) -> Self {
        match Instant::now().checked_add(timeout) {
            Some(d) => Self::with_deadline(d),
            None => Self::new(),
        }
    }

    /// Asks every decode holding a clone to stop at its next check. Idempotent.
    pub fn cancel(&self) {
        self.inner.cancelled.store(true, Ordering::Relaxed);
    }

    pub fn is_cancelled(&self) -> bool {
        self.inner.cancelled.load(Ordering::Relaxed)
    }

    pub fn deadline(&self) -> Option<Instant> {
        self.inner.deadline
    }

    /// `Err(Cancelled)` or `Err(DeadlineExceeded)` once the decode should stop. Cancellation
    /// wins: a caller that cancelled wants to know it was heard.
    pub fn check(&self) -> Result<(), MediaError> {
        if self.is_cancelled() {
            return Err(MediaError::Cancelled);
        }
        match self.inner.deadline {
            Some(d) if Instant::now() >= d => Err(MediaError::DeadlineExceeded),
            _ => Ok(()),
        }
    }

    /// A guard that cancels this interrupt when dropped. An async caller holds it across the
    /// `.await` on the blocking decode: when the request future is dropped (client gone,
    /// request timeout), the guard goes with it and the decode stops instead of running on.
    pub fn cancel_on_drop(&self) -> CancelOnDrop {
        CancelOnDrop(Some(self.clone()))
    }
}

/// Cancels its [`Interrupt`] on drop unless [`CancelOnDrop::disarm`]ed.
#[derive(Debug)]
#[must_use = "dropping the guard at once cancels the interrupt"]
pub struct CancelOnDrop(Option<Interrupt>);

impl CancelOnDrop {
    /// The work finished: dropping no longer cancels (other clones may still be in use).
    pub fn disarm(mut self) {
        self.0 = None;
    }
}

impl Drop for CancelOnDrop {
    fn drop(&mut self) {
        if let Some(i) = self.0.take() {
            i.cancel();
        }
    }
}
