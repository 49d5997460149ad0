//! The sentence-encoder seam of the embedding labeler.
//!
//! Why a trait: the matcher only needs "texts in, unit vectors out", while the engine that runs
//! the encoder is a deployment choice (candle on CUDA machines, ONNX Runtime on CPU-only ones).
//! Keeping the engine behind this trait lets both run the very same matcher, so the labeler that
//! is evaluated is the labeler that is served, whatever the engine.

use crate::ModelError;

/// A sentence encoder: mean-pooled, L2-normalised embeddings.
///
/// Implementations are blocking (they run model work on the calling thread or their own pool);
/// callers on an async runtime go through the service's blocking-backend adapter.
pub trait SentenceEncoder: Send + Sync {
    /// The engine, for logs and `/readyz` ("candle", "onnx").
    fn engine(&self) -> &str;
    /// Embedding dimension.
    fn dim(&self) -> usize;
    /// One unit-L2 embedding per text, in order, computed in one batched pass (padding with an
    /// attention mask), so that all clauses of all answers of a round cost one forward call.
    /// An empty input gives an empty output.
    fn encode(&self, texts: &[&str]) -> Result<Vec<Vec<f32>>, ModelError>;
}

/// Groups of text indices, each group run as one padded batch: both encoder engines use it, so
/// that a round's clauses (two words to thirty) do not all pay for the longest. Indices sorted by
/// length, cut where the padded cost `size × longest` plus `overhead` per group is smallest
/// (exact, by dynamic programming over the sorted lengths; rounds have tens of texts).
pub(crate) fn length_groups(lens: &[usize], overhead: usize) -> Vec<Vec<usize>> {
    let mut order: Vec<usize> = (0..lens.len()).collect();
    order.sort_by_key(|&i| lens[i]);
    let n = order.len();
    // best[j]: cheapest cost of the first j sorted texts; cut[j]: where its last group starts.
    let mut best = vec![usize::MAX; n + 1];
    let mut cut = vec![0; n + 1];
    best[0] = 0;
    for j in 1..=n {
        let longest = lens[order[j - 1]];
        for i in 0..j {
            let c = best[i] + (j - i) * longest + overhead;
            if c < best[j] {
                best[j] = c;
                cut[j] = i;
            }
        }
    }
    let mut groups = Vec::new();
    let mut j = n;
    while j > 0 {
        groups.push(order[cut[j]..j].to_vec());
        j = cut[j];
    }
    groups.reverse();
    groups
}

#[cfg(test)]
mod tests {
    use super::length_groups;

    #[test]
    fn length_groups_cover_every_text_once_and_cut_where_padding_costs() {
        // Lengths 3,3,4 and 20,21: two groups beat one (5 x 21 = 105 vs 12 + 42 + overhead).
        let g = length_groups(&[20, 3, 4, 21, 3], 16);
        assert_eq!(g, vec![vec![1, 4, 2], vec![0, 3]]);
        // A huge overhead keeps one run.
        assert_eq!(length_groups(&[20, 3, 4], 1000).len(), 1);
        let lens: Vec<usize> = (0..40).map(|i| (i * 7919) % 37 + 2).collect();
        let mut seen: Vec<usize> = length_groups(&lens, 16).concat();
        seen.sort();
        assert_eq!(seen, (0..40).collect::<Vec<_>>());
        assert!(length_groups(&[], 16).is_empty());
    }

    /// The cases the candle engine's buckets were checked on (now the same function).
    #[test]
    fn one_long_row_and_many_short_ones_split_unless_a_call_is_dear() {
        assert_eq!(length_groups(&[5, 5, 5], 10), vec![vec![0, 1, 2]]);
        // Padding the short rows to 100 costs far more than a second call.
        let lens = [100, 8, 8, 8, 8, 8, 8, 8, 8];
        assert_eq!(
            length_groups(&lens, 10),
            vec![(1..9).collect::<Vec<_>>(), vec![0]]
        );
        // With a huge per-call cost everything goes into one call.
        assert_eq!(length_groups(&lens, 10_000).len(), 1);
    }
}
