//! The tracker's optimal assignment with a cost limit: ultralytics' `matching.linear_assignment`,
//! which calls `lap.lapjv(cost, extend_cost=True, cost_limit=thresh)`.
//!
//! `lap` turns the `n x m` cost matrix into an `(n + m) x (n + m)` one: the costs in the top
//! left, `cost_limit / 2` everywhere in the two off-diagonal blocks (leaving a row or a column
//! unmatched costs half the limit) and zeros in the bottom right, and solves that square
//! problem exactly. A pair is therefore matched only where it beats leaving both unmatched,
//! and the matching is the cheapest overall. Any exact solver of the same square problem gives
//! the same assignment when the optimum is unique; here it is `pathfinding`'s Kuhn-Munkres on
//! integer weights (costs in nanounits: the `f32` costs the tracker computes differ by more
//! than that whenever they differ at all).

use pathfinding::prelude::{kuhn_munkres_min, Matrix};

/// Costs are scaled to integers with this factor.
const SCALE: f64 = 1e9;

/// `(matches (row, col), unmatched rows, unmatched cols)`, each in increasing order.
pub type Assignment = (Vec<(usize, usize)>, Vec<usize>, Vec<usize>);

/// Matches rows to columns of `cost` (`rows x cols`, row-major) at a total cost that is
/// minimal when each unmatched row or column costs `limit / 2`.
pub fn linear_assignment(cost: &[f32], rows: usize, cols: usize, limit: f64) -> Assignment {
    if rows == 0 || cols == 0 {
        return (Vec::new(), (0..rows).collect(), (0..cols).collect());
    }
    let n = rows + cols;
    let half = (limit / 2.0 * SCALE).round() as i64;
    let mut w = vec![0i64; n * n];
    for r in 0..n {
        for c in 0..n {
            w[r * n + c] = match (r < rows, c < cols) {
                (true, true) => {
                    let v = cost[r * cols + c] as f64;
                    // A NaN cost (a degenerate box) is as bad as leaving both unmatched twice.
                    if v.is_finite() {
                        (v * SCALE).round() as i64
                    } else {
                        4 * half.max(1)
                    }
                }
                (false, false) => 0,
                _ => half,
            };
        }
    }
    let m = Matrix::from_vec(n, n, w).unwrap_or_else(|_| unreachable!("n * n values"));
    let (_, assign) = kuhn_munkres_min(&m);
    let mut matches = Vec::new();
    let mut unmatched_rows = Vec::new();
    let mut col_used = vec![false; cols];
    for (r, &c) in assign.iter().enumerate().take(rows) {
        if c < cols {
            matches.push((r, c));
            col_used[c] = true;
        } else {
            unmatched_rows.push(r);
        }
    }
    let unmatched_cols = (0..cols).filter(|&c| !col_used[c]).collect();
    (matches, unmatched_rows, unmatched_cols)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cheapest_total_not_greedy_and_the_limit_leaves_pairs_unmatched() {
        // Greedy would take (0, 0) at 0.1 and leave row 1 with 0.9; the optimum crosses.
        let cost = [0.1, 0.2, 0.15, 0.9];
        let (m, ur, uc) = linear_assignment(&cost, 2, 2, 0.8);
        assert_eq!(m, [(0, 1), (1, 0)]);
        assert!(ur.is_empty() && uc.is_empty());
        // Costs above the limit are never matched.
        let (m, ur, uc) = linear_assignment(&[0.85, 0.3], 1, 2, 0.8);
        assert_eq!((m, ur, uc), (vec![(0, 1)], vec![], vec![0]));
        let (m, ur, uc) = linear_assignment(&[0.9, 0.95, 0.99, 0.81], 2, 2, 0.8);
        assert_eq!((m, ur, uc), (vec![], vec![0, 1], vec![0, 1]));
        let (m, ur, uc) = linear_assignment(&[], 0, 3, 0.8);
        assert_eq!((m, ur, uc), (vec![], vec![], vec![0, 1, 2]));
    }
}
