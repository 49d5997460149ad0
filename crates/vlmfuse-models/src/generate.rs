//! The one generation loop of the in-process models. Every family (Qwen3-VL, VideoLLaVA, and
//! the ones to come) implements the small [`Decoder`] interface (a fresh cache, one causal pass
//! over the prompt, one token per row after it); [`generate`] drives it for a whole batch.
//!
//! Why one loop: the stop rule, the tie rule and the sampler used to live in three places that
//! disagreed (one kept the stop token, two dropped it). Here the stop token is never part of
//! [`Generated::tokens`]; it is reported in [`Generated::stop`], and
//! [`Generated::with_stop`] gives the ids as transformers' `generate` returns them.
//!
//! Greedy decoding takes the first maximum of each row (`torch.argmax`'s tie rule, which the
//! parity tests rely on); with a temperature, each row gets its own candle-transformers
//! [`LogitsProcessor`], all seeded alike, so a row's answer does not depend on its batch.

use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use candle_core::{DType, Tensor};
use candle_transformers::generation::LogitsProcessor;

use crate::ModelError;

/// A causal decoder over a batch: what [`generate`] needs of a model.
pub trait Decoder {
    /// The model inputs of a batch, as the family's processor builds them.
    type Inputs;
    /// Per-generation state (the KV cache of a batch).
    type Cache;

    /// Rows in `inputs`.
    fn rows(inputs: &Self::Inputs) -> usize;
    /// The longest row of `inputs`, in tokens (sizes the cache).
    fn max_len(inputs: &Self::Inputs) -> usize;
    /// A cache for `capacity` positions per row.
    fn new_cache(&self, capacity: usize) -> Self::Cache;
    /// The whole prompt of every row in one pass: next-token logits `[batch, vocab]`.
    fn prefill(&self, inputs: &Self::Inputs, cache: &mut Self::Cache)
        -> Result<Tensor, ModelError>;
    /// One token per row after [`prefill`](Self::prefill): the next logits `[batch, vocab]`.
    fn step(&self, tokens: &[u32], cache: &mut Self::Cache) -> Result<Tensor, ModelError>;
}

/// How to generate.
#[derive(Debug, Clone, PartialEq)]
pub struct GenerateOptions {
    /// Most tokens per row, the stop token not counted.
    pub max_new_tokens: usize,
    /// Ids that end a row.
    pub stop: Vec<u32>,
    /// Unset or below 1e-7: greedy.
    pub temperature: Option<f64>,
    pub top_p: Option<f64>,
    pub seed: u64,
    /// Keep the logits after the prompt ([`Generated::first_logits`]).
    pub keep_first_logits: bool,
    /// Keep the logits each generated token was chosen from ([`Generated::step_logits`]);
    /// `vocab` floats per token and row, so for dumps and tests, not for serving.
    pub keep_step_logits: bool,
}

impl GenerateOptions {
    /// Greedy decoding of up to `max_new_tokens`, stopping at any id of `stop`.
    pub fn greedy(max_new_tokens: usize, stop: &[u32]) -> Self {
        Self {
            max_new_tokens,
            stop: stop.to_vec(),
            temperature: None,
            top_p: None,
            seed: 0,
            keep_first_logits: false,
            keep_step_logits: false,
        }
    }

    fn is_greedy(&self) -> bool {
        self.temperature.is_none_or(|t| t < 1e-7)
    }
}

/// What one batch generated.
#[derive(Debug, Clone, PartialEq)]
pub struct Generated {
    /// Per row, the generated ids without the stop token.
    pub tokens: Vec<Vec<u32>>,
    /// Per row, the stop token that ended it (`None`: it ran to `max_new_tokens`).
    pub stop: Vec<Option<u32>>,
    /// Per row, the next-token logits after the prompt (empty unless asked for).
    pub first_logits: Vec<Vec<f32>>,
    /// Per row, the logits each of its tokens (the stop token included) was chosen from, in
    /// order (empty unless asked for).
    pub step_logits: Vec<Vec<Vec<f32>>>,
    /// Prefill of the whole batch (vision tower included).
    pub prefill: Duration,
    /// Every step after the prefill.
    pub decode: Duration,
}

impl Generated {
    /// Row `r`'s ids with its stop token, as transformers' `generate` returns them.
    pub fn with_stop(&self, r: usize) -> Vec<u32> {
        let mut ids = self.tokens[r].clone();
        ids.extend(self.stop[r]);
        ids
    }
}

/// Generates for every row of `inputs`. A row ends at a stop id or after `max_new_tokens`;
/// the batch ends when every row has (finished rows are still fed their last id, so the batch
/// moves together, and their logits are no longer read). `cancel` is checked before the
/// prefill and between steps; a cancelled generation is a [`ModelError::Timeout`].
pub fn generate<D: Decoder>(
    model: &D,
    inputs: &D::Inputs,
    opts: &GenerateOptions,
    cancel: Option<&AtomicBool>,
) -> Result<Generated, ModelError> {
    let mut cache = model.new_cache(D::max_len(inputs) + opts.max_new_tokens + 1);
    generate_with(model, inputs, &mut cache, opts, cancel)
}

/// [`generate`] with a cache the caller owns (reused across calls: the prefill resets it).
pub fn generate_with<D: Decoder>(
    model: &D,
    inputs: &D::Inputs,
    cache: &mut D::Cache,
    opts: &GenerateOptions,
    cancel: Option<&AtomicBool>,
) -> Result<Generated, ModelError> {
    let t0 = Instant::now();
    let rows = D::rows(inputs);
    let cancelled = || ModelError::Timeout {
        what: "generation (cancelled)".into(),
        after: t0.elapsed(),
    };
    let is_cancelled = || cancel.is_some_and(|c| c.load(Ordering::Relaxed));
    let mut out = Generated {
        tokens: vec![Vec::new(); rows],
        stop: vec![None; rows],
        first_logits: Vec::new(),
        step_logits: Vec::new(),
        prefill: Duration::ZERO,
        decode: Duration::ZERO,
    };
    if opts.max_new_tokens == 0 || rows == 0 {
        return Ok(out);
    }
    if is_cancelled() {
        return Err(cancelled());
    }
    let mut logits = model.prefill(inputs, cache)?.to_dtype(DType::F32)?;
    if opts.keep_first_logits {
        out.first_logits = logits.to_vec2::<f32>()?;
    }
    out.prefill = t0.elapsed();
    let t1 = Instant::now();
    let mut samplers: Vec<LogitsProcessor> = if opts.is_greedy() {
        Vec::new()
    } else {
        (0..rows)
            .map(|_| LogitsProcessor::new(opts.seed, opts.temperature, opts.top_p))
            .collect()
    };
    let mut done = vec![false; rows];
    if opts.keep_step_logits {
        out.step_logits = vec![Vec::new(); rows];
    }
    loop {
        if is_cancelled() {
            return Err(cancelled());
        }
        if opts.keep_step_logits {
            let all = logits.to_vec2::<f32>()?;
            for (r, row) in all.into_iter().enumerate() {
                if !done[r] {
                    out.step_logits[r].push(row);
                }
            }
        }
        let next: Vec<u32> = if samplers.is_empty() {
            argmax_rows(&logits)?
        } else {
            samplers
                .iter_mut()
                .enumerate()
                .map(|(r, s)| s.sample(&logits.get(r)?))
                .collect::<Result<_, _>>()?
        };
        for (r, &t) in next.iter().enumerate() {
            if done[r] {
                continue;
            }
            if opts.stop.contains(&t) {
                out.stop[r] = Some(t);
                done[r] = true;
            } else {
                out.tokens[r].push(t);
                done[r] = out.tokens[r].len() >= opts.max_new_tokens;
            }
        }
        if done.iter().all(|&d| d) {
            break;
        }
        logits = model.step(&next, cache)?.to_dtype(DType::F32)?;
    }
    out.decode = t1.elapsed();
    Ok(out)
}

/// Index of the largest value of each row of `[batch, vocab]` logits, the first one on ties
/// (`torch.argmax`'s rule; candle's `argmax` does not promise one).
pub fn argmax_rows(logits: &Tensor) -> Result<Vec<u32>, ModelError> {
    let rows = logits.to_dtype(DType::F32)?.to_vec2::<f32>()?;
    Ok(rows
        .iter()
        .map(|r| {
            let mut best = 0;
            for (i, &x) in r.iter().enumerate() {
                if x > r[best] {
                    best = i;
                }
            }
            best as u32
        })
        .collect())
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::Device;

    /// A decoder whose next token is a fixed function of the last one: after token `t` it
    /// prefers `(t + 1) % vocab`. A row's prompt is one token.
    struct Counter {
        vocab: usize,
    }

    impl Counter {
        fn logits(&self, last: &[u32]) -> Tensor {
            let mut v = vec![0f32; last.len() * self.vocab];
            for (r, &t) in last.iter().enumerate() {
                v[r * self.vocab + (t as usize + 1) % self.vocab] = 5.0;
            }
            Tensor::from_vec(v, (last.len(), self.vocab), &Device::Cpu).unwrap()
        }
    }

    impl Decoder for Counter {
        type Inputs = Vec<u32>;
        type Cache = usize;
        fn rows(inputs: &Vec<u32>) -> usize {
            inputs.len()
        }
        fn max_len(_: &Vec<u32>) -> usize {
            1
        }
        fn new_cache(&self, _: usize) -> usize {
            0
        }
        fn prefill(&self, inputs: &Vec<u32>, cache: &mut usize) -> Result<Tensor, ModelError> {
            *cache = 1;
            Ok(self.logits(inputs))
        }
        fn step(&self, tokens: &[u32], cache: &mut usize) -> Result<Tensor, ModelError> {
            *cache += 1;
            Ok(self.logits(tokens))
        }
    }

    #[test]
    fn rows_stop_on_their_own_and_the_stop_id_is_reported_not_kept() {
        let m = Counter { vocab: 10 };
        // Row 0 counts 1, 2, 3 and meets 4; row 1 goes 6, 7, 8, 9, 0, 1 and never does.
        let g = generate(&m, &vec![0, 5], &GenerateOptions::greedy(6, &[4]), None).unwrap();
        assert_eq!(g.tokens[0], vec![1, 2, 3]);
        assert_eq!(g.stop[0], Some(4));
        assert_eq!(g.with_stop(0), vec![1, 2, 3, 4]);
        assert_eq!(g.tokens[1], vec![6, 7, 8, 9, 0, 1]);
        assert_eq!(g.stop[1], None);
        assert_eq!(g.with_stop(1), g.tokens[1]);
    }

    #[test]
    fn zero_tokens_and_cancellation() {
        let m = Counter { vocab: 10 };
        let g = generate(&m, &vec![0], &GenerateOptions::greedy(0, &[]), None).unwrap();
        assert_eq!(g.tokens, vec![Vec::<u32>::new()]);
        let cancel = AtomicBool::new(true);
        let e = generate(
            &m,
            &vec![0],
            &GenerateOptions::greedy(3, &[]),
            Some(&cancel),
        );
        assert!(matches!(e, Err(ModelError::Timeout { .. })));
    }

    #[test]
    fn sampling_is_seeded_and_keeps_first_logits() {
        let m = Counter { vocab: 10 };
        let opts = GenerateOptions {
            temperature: Some(0.7),
            seed: 7,
            keep_first_logits: true,
            ..GenerateOptions::greedy(5, &[])
        };
        let a = generate(&m, &vec![0, 0], &opts, None).unwrap();
        let b = generate(&m, &vec![0, 0], &opts, None).unwrap();
        assert_eq!(a.tokens, b.tokens);
        // Each row has its own sampler seeded alike: the same prompt gives the same answer.
        assert_eq!(a.tokens[0], a.tokens[1]);
        assert_eq!(a.first_logits.len(), 2);
        assert_eq!(a.first_logits[0][1], 5.0);
    }

    #[test]
    fn argmax_takes_the_first_maximum() {
        let t = Tensor::new(&[[1f32, 3., 3.], [5., 0., 5.]], &Device::Cpu).unwrap();
        assert_eq!(argmax_rows(&t).unwrap(), vec![1, 0]);
    }
}
