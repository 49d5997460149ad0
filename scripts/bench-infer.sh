#!/usr/bin/env bash
# /v1/infer's stage breakdown on CPU (issue 14): a release `vlmfuse serve` with the ONNX CLIP
# embedder (full-size ViT-B/32, random weights), three remote reporters on a loopback fake
# OpenAI server that answers at once, and the default embedding labeler (MiniLM on ONNX
# Runtime); a 20 s 720p clip with a keyframe every second, posted REQS times one after another.
# Prints each stage's median from the responses' `timings_ms`; the target is decode + embed +
# label + fuse <= 600 ms.
#
#   PYTHON (python3: needs torch + transformers only to write the bench model once)
#   REQS (20) THREADS (2: embedder and labeler threads) DECODE_THREADS (1) PORT (18080)
#   BENCH_DIR (a temporary dir)   CARGO_TARGET_DIR as usual   VLMFUSE_BIN (a built binary: no build)
#
# Not run in CI (the bench model needs torch).
set -euo pipefail
cd "$(dirname "$0")/.."
PY="${PYTHON:-python3}"
REQS="${REQS:-20}"; THREADS="${THREADS:-2}"; DECODE_THREADS="${DECODE_THREADS:-1}"
PORT="${PORT:-18080}"; FAKE_PORT=$((PORT + 1))
OUT="${BENCH_DIR:-$(mktemp -d)}"; mkdir -p "$OUT"

source scripts/bench/clip-model.sh

if [ -n "${VLMFUSE_BIN:-}" ]; then BIN="$VLMFUSE_BIN"; else
  cargo build --release -p vlmfuse --bin vlmfuse
  BIN="${CARGO_TARGET_DIR:-target}/release/vlmfuse"
fi

rm -rf "$OUT/data"
{
  cat <<TOML
reporters = ["vlaad", "videollama2", "videollava"]
[server]
listen = "127.0.0.1:$PORT"
data_dir = "$OUT/data"
[media]
decode_threads = $DECODE_THREADS
[embedder]
weights = { path = "$MODEL" }
backend = "onnx"
threads = $THREADS
[labeler]
kind = "embedding"
encoder = "onnx"
threads = $THREADS
TOML
  for m in vlaad videollama2 videollava; do
    cat <<TOML
[[reporter]]
kind = "openai"
name = "$m"
base_url = "http://127.0.0.1:$FAKE_PORT"
model = "$m"
mode = "video_url"
video_url_template = "file://{path}"
TOML
  done
} > "$OUT/config.toml"

"$PY" scripts/bench/fake_openai.py "$FAKE_PORT" & FAKE=$!
"$BIN" serve --config "$OUT/config.toml" > "$OUT/server.log" 2>&1 & SERVER=$!
trap 'kill $SERVER $FAKE 2>/dev/null || true' EXIT
for _ in $(seq 1 600); do
  curl -fsS "http://127.0.0.1:$PORT/readyz" >/dev/null 2>&1 && break
  kill -0 "$SERVER" 2>/dev/null || { cat "$OUT/server.log"; exit 1; }
  sleep 0.1
done
curl -fsS "http://127.0.0.1:$PORT/readyz" >/dev/null || { echo "server not ready"; cat "$OUT/server.log"; exit 1; }

echo "== /v1/infer: $REQS requests + 1 warm-up, embedder/labeler threads $THREADS, decode threads $DECODE_THREADS (load: $(cut -d' ' -f1-3 /proc/loadavg))"
files=()
for i in $(seq 0 "$REQS"); do
  curl -fsS -F "video=@$CLIP;type=video/mp4" "http://127.0.0.1:$PORT/v1/infer" > "$OUT/resp-$i.json"
  files+=("$OUT/resp-$i.json")
done
"$PY" scripts/bench/infer_summary.py "${files[@]}"
echo "results: $OUT"
