//! The types every vlmfuse crate shares, so that each has one home:
//!
//! * [`Ontology`] and [`Label`]: the label set, with the descriptions labelers show models;
//! * [`Frame`] and [`FrameRef`]: decoded RGB frames with their presentation time;
//! * [`chat`] (feature `chat`): the OpenAI-compatible chat client with the one retry policy, which
//!   the remote reporter and the remote LLM labeler both wrap;
//! * [`backend`] (feature `backend`): the adapter that gives a blocking local backend (an
//!   embedder, an in-process VLM, a labeler model) dedicated threads, a bounded queue, async
//!   calls, timeouts and cancellation.
//!
//! The first two are plain data with no I/O; `vlmfuse-fusion` depends on this crate with default
//! features off and sees nothing else.

mod frame;
pub mod ontology;

#[cfg(feature = "backend")]
pub mod backend;
#[cfg(feature = "chat")]
pub mod chat;

pub use frame::{Frame, FrameError, FrameRef};
pub use ontology::{Label, Ontology, OntologyError, PAPER_LABELS};

#[cfg(feature = "backend")]
pub use backend::{BackendError, BackendPool, PoolConfig};
#[cfg(feature = "chat")]
pub use chat::{ChatClient, ChatError, ChatReply, RetryPolicy};
