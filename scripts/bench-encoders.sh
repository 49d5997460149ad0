#!/usr/bin/env bash
# The encoder benchmark of issue 14, in one run: CLIP ViT-B/32 (random weights, full size) on N
# frames of a 20 s 720p clip (keyframe every second) through vlmfuse's ONNX Runtime backend,
# onnxruntime in Python, vlmfuse's candle backend and torch, all on THREADS threads; then the
# MiniLM label-stage encoder (three typical answers, one batch) on ONNX Runtime and candle.
#
# Ratios are only meaningful within one run: the engines alternate in ROUNDS rounds (Rust, then
# Python, again), and each median is over every timed run of that engine.
#
#   PYTHON       a Python with torch, transformers, onnxruntime and pillow (a reference venv
#                outside the repository; default: python3)
#   THREADS (2) FRAMES (8) REPS (10) ROUNDS (2) SHORT_SIDE (0: the clip's 720 rows)
#   BENCH_DIR    where the clip, the frames and the JSON results go (default: a temporary dir)
#   CARGO_TARGET_DIR   as usual (a shared release dir saves the dependency build)
#
# Not run in CI (it needs torch and a ~700 MB model that scripts/onnx/make_bench_model.py writes
# into the asset cache).
set -euo pipefail
cd "$(dirname "$0")/.."
PY="${PYTHON:-python3}"
THREADS="${THREADS:-2}"; FRAMES="${FRAMES:-8}"; REPS="${REPS:-10}"; ROUNDS="${ROUNDS:-2}"
SHORT_SIDE="${SHORT_SIDE:-0}"
OUT="${BENCH_DIR:-$(mktemp -d)}"
mkdir -p "$OUT"

source scripts/bench/clip-model.sh

cargo build --release -p vlmfuse-models --example onnx_embed_bench \
  -p vlmfuse-labeler --example onnx_encoder_bench
BIN="${CARGO_TARGET_DIR:-target}/release/examples"

echo "== CLIP context embedder: $FRAMES frames, $THREADS threads, $ROUNDS rounds x $REPS runs (load: $(cut -d' ' -f1-3 /proc/loadavg))"
rust=(); py=()
for r in $(seq 1 "$ROUNDS"); do
  RAYON_NUM_THREADS="$THREADS" "$BIN/onnx_embed_bench" --model "$MODEL" --clip "$CLIP" \
    --frames "$FRAMES" --short-side "$SHORT_SIDE" --threads "$THREADS" --reps "$REPS" \
    --out "$OUT/rust-$r.json" --dump-frames "$OUT/frames.rgb"
  OMP_NUM_THREADS="$THREADS" "$PY" scripts/onnx/bench_reference.py measure --model "$MODEL" \
    --frames "$OUT/frames.rgb" --threads "$THREADS" --reps "$REPS" --out "$OUT/python-$r.json"
  rust+=("$OUT/rust-$r.json"); py+=("$OUT/python-$r.json")
done
"$PY" scripts/onnx/bench_reference.py summary --rust "${rust[@]}" --python "${py[@]}" \
  --out "$OUT/summary.json"

echo
echo "== MiniLM sentence encoder (label stage), $THREADS threads"
RAYON_NUM_THREADS="$THREADS" "$BIN/onnx_encoder_bench" --threads "$THREADS" --reps 30
echo
echo "results: $OUT"
