//! CPU fast paths for the element-wise ops that dominate a small VLM's prefill on CPU.
//!
//! candle 0.11's CPU softmax, tanh-GELU and SiLU call libm's scalar `expf`/`tanhf` per element
//! (9–17 ns each): on the mid-size benchmark model the vision tower's tanh-GELU alone took more
//! time than its matmuls. Here `exp` is a branch-free range reduction plus a degree-7
//! polynomial (relative error below 2e-7, about one f32 ulp) that LLVM vectorises, as torch's
//! Sleef kernels are vectorised. Only contiguous f32 tensors on the CPU take these paths;
//! everything else (GPU, half types) goes to candle's own ops, so results on CUDA are candle's.

use candle_core::{CpuStorage, CustomOp1, DType, Layout, Result, Shape, Tensor};

const LOG2E: f32 = std::f32::consts::LOG2_E;
// ln 2 split in a high part exact in f32 and the rest (Cody–Waite), so `x - n ln2` loses no bits.
const LN2_HI: f32 = 0.693_145_75;
const LN2_LO: f32 = 1.428_606_8e-6;

/// `exp(x)` for f32 without branches: 0 below -87.3 (where f32 exp underflows to subnormals),
/// and finite (about 2e38) from 88.3 up, where the callers only need "huge".
#[inline(always)]
pub fn exp_f32(x: f32) -> f32 {
    let xc = x.clamp(-87.3, 88.3);
    // Round to nearest with the 1.5 * 2^23 trick: the integer lands in the low mantissa bits,
    // so both n and 2^n come from bit operations (which vectorise; float-to-int `as` does not).
    let t = xc * LOG2E + 12_582_912.0;
    let n = t - 12_582_912.0;
    let ni = t.to_bits() as i32 - 0x4B40_0000;
    let r = xc - n * LN2_HI - n * LN2_LO;
    let p = 1.0
        + r * (1.0
            + r * (0.5
                + r * (1.0 / 6.0
                    + r * (1.0 / 24.0 + r * (1.0 / 120.0 + r * (1.0 / 720.0 + r / 5040.0))))));
    let scale = f32::from_bits(((ni + 127) as u32) << 23);
    if x < -87.3 {
        0.0
    } else {
        p * scale
    }
}

/// `tanh(y) = 1 - 2 / (exp(2y) + 1)`, exact at the saturated ends.
#[inline(always)]
fn tanh_f32(y: f32) -> f32 {
    1.0 - 2.0 / (exp_f32(2.0 * y) + 1.0)
}

#[derive(Clone, Copy)]
enum Kind {
    GeluTanh,
    Silu,
    Softmax,
}

struct Fast(Kind);

/// A reduction over 8 independent lanes, then across them: an ordered f32 fold is a serial
/// dependency chain the compiler may not reorder, eight lanes vectorise.
#[inline(always)]
fn lanes(v: &[f32], init: f32, f: impl Fn(f32, f32) -> f32) -> f32 {
    let mut acc = [init; 8];
    let chunks = v.chunks_exact(8);
    let tail = chunks.remainder();
    for c in chunks {
        for i in 0..8 {
            acc[i] = f(acc[i], c[i]);
        }
    }
    let mut r = tail.iter().fold(init, |a, &b| f(a, b));
    for a in acc {
        r = f(r, a);
    }
    r
}

fn map(src: &[f32], f: impl Fn(f32) -> f32) -> Vec<f32> {
    src.iter().map(|&v| f(v)).collect()
}

impl CustomOp1 for Fast {
    fn name(&self) -> &'static str {
        match self.0 {
            Kind::GeluTanh => "vlmfuse-gelu-tanh",
            Kind::Silu => "vlmfuse-silu",
            Kind::Softmax => "vlmfuse-softmax-last-dim",
        }
    }

    fn cpu_fwd(&self, s: &CpuStorage, l: &Layout) -> Result<(CpuStorage, Shape)> {
        let CpuStorage::F32(v) = s else {
            candle_core::bail!("{}: f32 only", self.name())
        };
        let Some((a, b)) = l.contiguous_offsets() else {
            candle_core::bail!("{}: contiguous input only", self.name())
        };
        let src = &v[a..b];
        let out = match self.0 {
            Kind::GeluTanh => {
                const C: f32 = 0.797_884_6; // sqrt(2 / pi)
                map(src, |x| {
                    0.5 * x * (1.0 + tanh_f32(C * (x + 0.044_715 * x * x * x)))
                })
            }
            Kind::Silu => map(src, |x| x / (1.0 + exp_f32(-x))),
            Kind::Softmax => {
                let d = l.dims().last().copied().unwrap_or(1).max(1);
                let mut out = vec![0f32; src.len()];
                for (row, dst) in src.chunks_exact(d).zip(out.chunks_exact_mut(d)) {
                    let max = lanes(row, f32::NEG_INFINITY, f32::max);
                    for (o, &x) in dst.iter_mut().zip(row) {
                        *o = exp_f32(x - max);
                    }
                    // Summed apart from the exp loop so that loop vectorises.
                    let sum = lanes(dst, 0.0, |a, b| a + b);
                    let inv = 1.0 / sum;
                    dst.iter_mut().for_each(|o| *o *= inv);
                }
                out
            }
        };
        Ok((CpuStorage::F32(out), l.shape().clone()))
    }
}

fn fast_path(x: &Tensor) -> bool {
    x.device().is_cpu() && x.dtype() == DType::F32
}

/// GELU with the tanh approximation (`gelu_pytorch_tanh`).
pub fn gelu_tanh(x: &Tensor) -> Result<Tensor> {
    if fast_path(x) {
        x.contiguous()?.apply_op1_no_bwd(&Fast(Kind::GeluTanh))
    } else {
        x.gelu()
    }
}

/// SiLU, `x * sigmoid(x)`.
pub fn silu(x: &Tensor) -> Result<Tensor> {
    if fast_path(x) {
        x.contiguous()?.apply_op1_no_bwd(&Fast(Kind::Silu))
    } else {
        x.silu()
    }
}

/// Softmax over the last dimension.
pub fn softmax_last_dim(x: &Tensor) -> Result<Tensor> {
    if fast_path(x) {
        x.contiguous()?.apply_op1_no_bwd(&Fast(Kind::Softmax))
    } else {
        candle_nn::ops::softmax_last_dim(x)
    }
}

/// An activation by transformers' name, with the fast paths where there is one.
pub fn activation(act: candle_nn::Activation, x: &Tensor) -> Result<Tensor> {
    use candle_nn::Activation as A;
    match act {
        A::GeluPytorchTanh | A::NewGelu => gelu_tanh(x),
        A::Silu => silu(x),
        other => x.apply(&other),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::Device;

    #[test]
    fn exp_is_within_two_ulps_of_libm() {
        let mut worst = 0f64;
        let mut x = -87.0f32;
        while x < 88.0 {
            let (a, b) = (exp_f32(x) as f64, (x as f64).exp());
            worst = worst.max(((a - b) / b).abs());
            x += 0.0137;
        }
        assert!(worst < 2.5e-7, "relative error {worst}");
        assert_eq!(exp_f32(-1e30), 0.0);
        assert_eq!(exp_f32(f32::MIN), 0.0);
        assert_eq!(exp_f32(0.0), 1.0);
        assert!(exp_f32(1e30).is_finite());
    }

    #[test]
    fn fast_ops_match_candle() {
        let dev = Device::Cpu;
        let x = Tensor::arange(-600f32, 600., &dev)
            .unwrap()
            .affine(0.02, 0.0)
            .unwrap()
            .reshape((4, 300))
            .unwrap();
        let close = |a: Tensor, b: Tensor, tol: f32| {
            let d = (a - b)
                .unwrap()
                .abs()
                .unwrap()
                .max_all()
                .unwrap()
                .to_scalar::<f32>()
                .unwrap();
            assert!(d < tol, "max diff {d}");
        };
        close(gelu_tanh(&x).unwrap(), x.gelu().unwrap(), 2e-6);
        close(silu(&x).unwrap(), x.silu().unwrap(), 2e-6);
        close(
            softmax_last_dim(&x).unwrap(),
            candle_nn::ops::softmax_last_dim(&x).unwrap(),
            1e-7,
        );
        // Masked scores (f32::MIN) get exactly zero weight; rows still sum to one.
        let m = Tensor::new(&[[0f32, f32::MIN, 1.0], [f32::MIN, f32::MIN, 2.0]], &dev).unwrap();
        let s = softmax_last_dim(&m).unwrap().to_vec2::<f32>().unwrap();
        assert_eq!(s[0][1], 0.0);
        assert_eq!(s[1], vec![0.0, 0.0, 1.0]);
        // Non-contiguous input and a non-f32 dtype take the generic paths.
        let t = x.t().unwrap();
        close(gelu_tanh(&t).unwrap(), t.gelu().unwrap(), 2e-6);
        let h = x.to_dtype(DType::BF16).unwrap();
        assert_eq!(gelu_tanh(&h).unwrap().dtype(), DType::BF16);
    }
}
