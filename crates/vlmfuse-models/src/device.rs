//! Device selection from a config string, so the same config file works on CPU-only builds and
//! fails loudly (instead of silently falling back to CPU) when a GPU was asked for.

use candle_core::Device;

use crate::ModelError;

/// Parses `"cpu"`, `"cuda"` (= `cuda:0`) or `"cuda:N"`.
pub fn parse_device(spec: &str) -> Result<Device, ModelError> {
    let s = spec.trim().to_ascii_lowercase();
    if s == "cpu" {
        return Ok(Device::Cpu);
    }
    if s == "metal" || s.starts_with("metal:") || s == "mps" {
        return Err(ModelError::Device(format!(
            "`{spec}`: Metal is not supported by vlmfuse; use \"cpu\" or \"cuda[:N]\""
        )));
    }
    let ordinal = if s == "cuda" {
        Some(0)
    } else if let Some(n) = s.strip_prefix("cuda:") {
        Some(n.parse::<usize>().map_err(|_| {
            ModelError::Device(format!("`{spec}`: expected cuda:N with N a GPU index"))
        })?)
    } else {
        None
    };
    match ordinal {
        Some(n) => cuda(spec, n),
        None => Err(ModelError::Device(format!(
            "unknown device `{spec}`; expected \"cpu\", \"cuda\" or \"cuda:N\""
        ))),
    }
}

#[cfg(feature = "cuda")]
fn cuda(spec: &str, n: usize) -> Result<Device, ModelError> {
    Device::new_cuda(n).map_err(|e| ModelError::Device(format!("`{spec}`: {e}")))
}

#[cfg(not(feature = "cuda"))]
fn cuda(spec: &str, _n: usize) -> Result<Device, ModelError> {
    Err(ModelError::Device(format!(
        "`{spec}`: this build has no CUDA support; rebuild with `--features cuda` or use \"cpu\""
    )))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cpu_parses() {
        assert!(parse_device("cpu").unwrap().is_cpu());
        assert!(parse_device(" CPU ").unwrap().is_cpu());
    }

    #[test]
    fn metal_is_refused_clearly() {
        let e = parse_device("metal").unwrap_err();
        assert_eq!(e.kind(), "device");
        assert!(e.to_string().contains("not supported"), "{e}");
    }

    #[test]
    fn garbage_is_refused() {
        assert!(parse_device("tpu").is_err());
        assert!(parse_device("cuda:x")
            .unwrap_err()
            .to_string()
            .contains("cuda:N"));
    }

    #[cfg(not(feature = "cuda"))]
    #[test]
    fn cuda_without_feature_says_so() {
        for s in ["cuda", "cuda:1"] {
            let e = parse_device(s).unwrap_err();
            assert!(e.to_string().contains("--features cuda"), "{e}");
        }
    }
}
