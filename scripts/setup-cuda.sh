#!/usr/bin/env bash
# Installs a CUDA build toolchain from PyPI wheels (no Debian CUDA toolkit is reachable here):
# nvcc + cicc + ptxas, the runtime/CRT/CCCL headers, and the libraries candle's cudarc links
# against (cuBLAS, cuRAND, NVRTC), into a cache outside the repository. No GPU is needed: this
# is what `cargo check/build --features cuda` needs to compile candle's kernels.
#
# Idempotent: a cache whose stamp lists the same pinned wheels is not touched again.
#
#   VLMFUSE_CUDA   cache root (default: $HOME/.cache/vlmfuse-cuda)
#   --print-env    only print the environment (the cache must exist)
#
# cudarc 0.19.10 knows CUDA APIs up to 13.4 and refuses to guess from nvcc 13.5, so the printed
# environment pins its bindings to 13.4 (CUDARC_CUDA_VERSION); 13.5 drivers and libraries serve
# the 13.4 API.
#
# Prints, on stdout, the environment to `eval` before cargo:
#   eval "$(bash scripts/setup-cuda.sh)" && cargo check -p vlmfuse-models --features cuda
#
# Exit status: 0 on success; 3 when the registry cannot be reached; anything else is a failure.
set -euo pipefail

ROOT="${VLMFUSE_CUDA:-$HOME/.cache/vlmfuse-cuda}"
SITE="$ROOT/site"
STAMP="$ROOT/.installed"
# One CUDA line (13.x) for compiler, headers and libraries; bump together.
WHEELS=(
  "nvidia-cuda-nvcc==13.5.37"
  "nvidia-nvvm==13.5.37"
  "nvidia-cuda-crt==13.5.37"
  "nvidia-cuda-runtime==13.5.37"
  "nvidia-cuda-cccl==13.3.5.0.6"
  "nvidia-cuda-nvrtc==13.5.37"
  "nvidia-cublas==13.10.0.20"
  "nvidia-curand==10.4.4.72"
)
WANT="$(printf '%s\n' "${WHEELS[@]}")"

log() { echo "setup-cuda: $*" >&2; }

install() {
  local py
  py="$(command -v python3 || true)"
  if [ -z "$py" ]; then log "python3 is needed to install the wheels"; exit 1; fi
  log "installing ${#WHEELS[@]} CUDA wheels into $SITE (about 1 GB download)"
  rm -rf "$SITE.tmp"
  local err
  if ! err=$("$py" -m pip install --quiet --no-deps --only-binary=:all: --target "$SITE.tmp" \
      "${WHEELS[@]}" 2>&1); then
    echo "$err" >&2
    rm -rf "$SITE.tmp"
    if echo "$err" | grep -qiE "connection|resolve|network|timed out|unreachable|No matching distribution|Could not find a version"; then
      log "registry unreachable or a wheel is missing"
      exit 3
    fi
    exit 1
  fi
  rm -rf "$SITE"
  mv "$SITE.tmp" "$SITE"
  local cu="$SITE/nvidia/cu13"
  # The wheels ship sonames only; linkers look for the unversioned names.
  for l in cudart cublas cublasLt curand nvrtc; do
    local so
    so="$(ls "$cu"/lib/lib$l.so.* 2>/dev/null | head -n1 || true)"
    [ -n "$so" ] && ln -sf "$(basename "$so")" "$cu/lib/lib$l.so"
  done
  # cudarc links libcuda, which only a driver installs. A stub library that exports nothing
  # lets the link succeed; cudarc resolves its symbols at run time, where the real driver is.
  mkdir -p "$cu/lib/stubs"
  if command -v cc >/dev/null; then
    echo 'void vlmfuse_cuda_stub(void) {}' > "$ROOT/stub.c"
    cc -shared -fPIC -Wl,-soname,libcuda.so.1 -o "$cu/lib/stubs/libcuda.so" "$ROOT/stub.c"
  fi
  printf '%s\n' "$WANT" > "$STAMP"
}

if [ "${1:-}" != "--print-env" ]; then
  if [ ! -f "$STAMP" ] || [ "$(cat "$STAMP")" != "$WANT" ]; then
    install
  else
    log "cache up to date: $ROOT"
  fi
fi

CU="$SITE/nvidia/cu13"
for f in "$CU/bin/nvcc" "$CU/include/cuda_runtime.h" "$CU/include/cublas_v2.h"; do
  if [ ! -e "$f" ]; then log "missing $f (rerun without --print-env)"; exit 1; fi
done
cat <<EOF
export CUDA_ROOT="$CU"
export CUDA_PATH="$CU"
export CUDA_HOME="$CU"
export CUDA_TOOLKIT_ROOT_DIR="$CU"
export PATH="$CU/bin:\$PATH"
export LIBRARY_PATH="$CU/lib:$CU/lib/stubs\${LIBRARY_PATH:+:\$LIBRARY_PATH}"
export LD_LIBRARY_PATH="$CU/lib\${LD_LIBRARY_PATH:+:\$LD_LIBRARY_PATH}"
export CUDA_COMPUTE_CAP=90
export CUDARC_CUDA_VERSION=13040
EOF
