//! The model half of the test tooling (`publish = false`): tiny random-weight models in the real
//! on-disk formats, the real-asset lookup and the labelers' evaluation. It sits apart from
//! `vlmfuse-testkit` because it needs candle, tokenizers and the labeler (and through it ONNX
//! Runtime): only the tests of the crates that run models (models, labeler, the service) pull it
//! in, so the engine's tests build none of that.
//!
//! * [`fixtures`]: tiny random-weight models (CLIP, Qwen3-VL, VideoLLaVA, HF cache layout);
//! * [`assets`]: where the small real models that PyPI packages ship were fetched to;
//! * [`labeler_eval`]: the labelers' data set, metrics and threshold tuning.

pub mod assets;
pub mod fixtures;
pub mod labeler_eval;
pub mod parity;
