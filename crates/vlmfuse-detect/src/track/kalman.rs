//! The constant-velocity Kalman filters of ultralytics' trackers
//! (`ultralytics/trackers/utils/kalman_filter.py`): state `(x, y, a|w, h)` plus velocities,
//! noise proportional to the box size (1/20 of it for positions, 1/160 for velocities).
//! ByteTrack measures `(cx, cy, aspect, h)` ([`Layout::Xyah`]); BoT-SORT `(cx, cy, w, h)`
//! ([`Layout::Xywh`]).

// Index loops over 4x4 and 8x8 arrays read like the matrix algebra they implement.
#![allow(clippy::needless_range_loop)]

pub type Mean = [f64; 8];
pub type Cov = [[f64; 8]; 8];

const STD_POS: f64 = 1.0 / 20.0;
const STD_VEL: f64 = 1.0 / 160.0;

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Layout {
    Xyah,
    Xywh,
}

impl Layout {
    /// Standard deviations of `(x, y, a|w, h)` in units of the box: `[pos; 4]` from `scale`
    /// times the size entries, and the aspect's fixed value in the XYAH layout.
    fn stds(self, m: &[f64], k: f64, aspect: f64) -> [f64; 4] {
        match self {
            Layout::Xyah => [k * m[3], k * m[3], aspect, k * m[3]],
            Layout::Xywh => [k * m[2], k * m[3], k * m[2], k * m[3]],
        }
    }

    pub fn initiate(self, z: [f64; 4]) -> (Mean, Cov) {
        let mut mean = [0.0; 8];
        mean[..4].copy_from_slice(&z);
        let p = self.stds(&z, 2.0 * STD_POS, 1e-2);
        let v = self.stds(&z, 10.0 * STD_VEL, 1e-5);
        (mean, diag(&p, &v))
    }

    /// One step: `x' = F x`, `P' = F P Fᵀ + Q` with `Q` from the state before the step.
    pub fn predict(self, mean: &Mean, cov: &Cov) -> (Mean, Cov) {
        let q = diag(
            &self.stds(mean, STD_POS, 1e-2),
            &self.stds(mean, STD_VEL, 1e-5),
        );
        let mut m = *mean;
        for i in 0..4 {
            m[i] += mean[i + 4];
        }
        // F P Fᵀ with F = [[I, I], [0, I]].
        let mut fp = *cov;
        for i in 0..4 {
            for j in 0..8 {
                fp[i][j] += cov[i + 4][j];
            }
        }
        let mut p = fp;
        for row in p.iter_mut() {
            for j in 0..4 {
                row[j] += row[j + 4];
            }
        }
        for i in 0..8 {
            p[i][i] += q[i][i];
        }
        (m, p)
    }

    /// Measurement update with `z` (`np.linalg.solve` for the gain, as ultralytics does).
    pub fn update(self, mean: &Mean, cov: &Cov, z: [f64; 4]) -> (Mean, Cov) {
        let r = self.stds(mean, STD_POS, 1e-1);
        let mut s = [[0.0; 4]; 4];
        for i in 0..4 {
            for j in 0..4 {
                s[i][j] = cov[i][j];
            }
            s[i][i] += r[i] * r[i];
        }
        // K = P Hᵀ S⁻¹, from S Kᵀ = (P Hᵀ)ᵀ.
        let mut rhs = [[0.0; 8]; 4];
        for i in 0..4 {
            for j in 0..8 {
                rhs[i][j] = cov[j][i];
            }
        }
        let kt = solve4(s, rhs);
        let mut m = *mean;
        let innov: Vec<f64> = (0..4).map(|i| z[i] - mean[i]).collect();
        for (j, mj) in m.iter_mut().enumerate() {
            *mj += (0..4).map(|i| innov[i] * kt[i][j]).sum::<f64>();
        }
        // P - K S Kᵀ.
        let mut ks = [[0.0; 4]; 8];
        for a in 0..8 {
            for b in 0..4 {
                ks[a][b] = (0..4).map(|i| kt[i][a] * s[i][b]).sum();
            }
        }
        let mut p = *cov;
        for a in 0..8 {
            for c in 0..8 {
                p[a][c] -= (0..4).map(|b| ks[a][b] * kt[b][c]).sum::<f64>();
            }
        }
        (m, p)
    }
}

fn diag(p: &[f64; 4], v: &[f64; 4]) -> Cov {
    let mut c = [[0.0; 8]; 8];
    for i in 0..4 {
        c[i][i] = p[i] * p[i];
        c[i + 4][i + 4] = v[i] * v[i];
    }
    c
}

/// Solves `A X = B` for a 4x4 `A` by Gaussian elimination with partial pivoting (LAPACK's
/// `gesv`, which `np.linalg.solve` calls, pivots the same way).
fn solve4(mut a: [[f64; 4]; 4], mut b: [[f64; 8]; 4]) -> [[f64; 8]; 4] {
    for col in 0..4 {
        let piv = (col..4)
            .max_by(|&i, &j| a[i][col].abs().total_cmp(&a[j][col].abs()))
            .unwrap_or(col);
        a.swap(col, piv);
        b.swap(col, piv);
        let d = a[col][col];
        if d == 0.0 {
            continue;
        }
        for r in col + 1..4 {
            let f = a[r][col] / d;
            if f == 0.0 {
                continue;
            }
            for c in col..4 {
                a[r][c] -= f * a[col][c];
            }
            for c in 0..8 {
                b[r][c] -= f * b[col][c];
            }
        }
    }
    let mut x = [[0.0; 8]; 4];
    for r in (0..4).rev() {
        for c in 0..8 {
            let s: f64 = (r + 1..4).map(|k| a[r][k] * x[k][c]).sum();
            x[r][c] = if a[r][r] == 0.0 {
                0.0
            } else {
                (b[r][c] - s) / a[r][r]
            };
        }
    }
    x
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_box_moving_at_constant_speed_is_followed_and_predicted() {
        for layout in [Layout::Xywh, Layout::Xyah] {
            let size = |w: f64, h: f64| match layout {
                Layout::Xywh => (w, h),
                Layout::Xyah => (w / h, h),
            };
            let (a, h) = size(40.0, 80.0);
            let (mut m, mut p) = layout.initiate([100.0, 200.0, a, h]);
            for t in 1..30 {
                (m, p) = layout.predict(&m, &p);
                (m, p) = layout.update(&m, &p, [100.0 + 5.0 * t as f64, 200.0, a, h]);
            }
            let (m2, _) = layout.predict(&m, &p);
            assert!((m[4] - 5.0).abs() < 0.05, "{layout:?} velocity {}", m[4]);
            assert!(
                (m2[0] - (100.0 + 5.0 * 30.0)).abs() < 0.5,
                "{layout:?} {}",
                m2[0]
            );
            // The covariance stays symmetric and positive on the diagonal.
            for i in 0..8 {
                assert!(p[i][i] > 0.0);
                for j in 0..8 {
                    assert!((p[i][j] - p[j][i]).abs() < 1e-9);
                }
            }
        }
    }

    #[test]
    fn solve_matches_a_known_system() {
        let a = [
            [0.0, 2.0, 0.0, 0.0],
            [1.0, 0.0, 0.0, 0.0],
            [0.0, 0.0, 4.0, 1.0],
            [0.0, 0.0, 1.0, 3.0],
        ];
        let mut b = [[0.0; 8]; 4];
        b[0][0] = 2.0;
        b[1][0] = 3.0;
        b[2][0] = 5.0;
        b[3][0] = 4.0;
        let x = solve4(a, b);
        let want = [3.0, 1.0, 1.0, 1.0];
        for i in 0..4 {
            assert!((x[i][0] - want[i]).abs() < 1e-12, "{:?}", x);
        }
    }
}
