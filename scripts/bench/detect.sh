#!/usr/bin/env bash
# Detector latency per frame, vlmfuse-detect against ultralytics' own ONNX path
# (onnxruntime-python), on the same 1280x720 frame (tests/data/parity/detect/frame_4_1280x720.png),
# one model after the other, in one run:
#
#   PYTHON=/work/venvs/ultralytics/bin/python scripts/bench/detect.sh [MODEL.onnx ...]
#
# Default models: the committed tiny YOLO11 (160 px) and, when present, a YOLO11n at 640 that
# `scripts/parity/yolo_detect.py --model yolo11n.yaml --imgsz 640 --out DIR` wrote
# ($YOLO11N, default /work/venvs/yolo11n-parity/model.onnx). Random weights: the speed is the
# architecture's. THREADS (default 2) is the intra-op thread count of both sessions.
set -euo pipefail
cd "$(dirname "$0")/../.."
PYTHON="${PYTHON:-python3}"
THREADS="${THREADS:-2}"
RUNS="${RUNS:-30}"
FRAME=tests/data/parity/detect/frame_4_1280x720.png
models=("$@")
if [ ${#models[@]} -eq 0 ]; then
  models=(tests/data/parity/detect/model.onnx)
  y="${YOLO11N:-/work/venvs/yolo11n-parity/model.onnx}"
  [ -f "$y" ] && models+=("$y")
fi
export ORT_DYLIB_PATH="${ORT_DYLIB_PATH:-${VLMFUSE_ASSETS:-$HOME/.cache/vlmfuse-assets}/onnxruntime/libonnxruntime.so.1.31.1}"
cargo build -q --release -p vlmfuse-detect --example bench
echo "machine: $(nproc) cores, $(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2 | xargs)"
for m in "${models[@]}"; do
  target/release/examples/bench "$m" "$FRAME" "$RUNS" "$THREADS"
  "$PYTHON" scripts/parity/yolo_detect.py --bench "$m" --threads "$THREADS"
done
