#!/usr/bin/env bash
# Runs schemathesis (PyPI) against a live `vlmfuse serve` from openapi.yaml: fails on any 5xx
# and on any response that breaks the documented schema or status codes.
#
#   scripts/schemathesis.sh [path/to/vlmfuse]     (default: target/debug/vlmfuse, built if absent)
#
# Environment: SCHEMATHESIS_VERSION (pinned below), VLMFUSE_ST_CACHE (venv location, default
# ~/.cache/vlmfuse/schemathesis), ST_MAX_EXAMPLES (default 30), ST_TIME_LIMIT_S (default 300).
set -euo pipefail

root="$(cd "$(dirname "$0")/.." && pwd)"
version="${SCHEMATHESIS_VERSION:-4.32.5}"
cache="${VLMFUSE_ST_CACHE:-${XDG_CACHE_HOME:-$HOME/.cache}/vlmfuse/schemathesis}"
venv="$cache/venv-$version"
max_examples="${ST_MAX_EXAMPLES:-30}"
time_limit="${ST_TIME_LIMIT_S:-300}"

# Idempotent install into a venv outside the repository.
if ! "$venv/bin/st" --version >/dev/null 2>&1; then
    mkdir -p "$cache"
    python3 -m venv "$venv"
    "$venv/bin/pip" install --quiet --upgrade pip
    "$venv/bin/pip" install --quiet "schemathesis==$version"
fi

bin="${1:-${CARGO_TARGET_DIR:-$root/target}/debug/vlmfuse}"
if [ ! -x "$bin" ]; then
    (cd "$root" && cargo build -p vlmfuse)
fi

data="$(mktemp -d)"
log="$data/server.log"
"$bin" serve --listen 127.0.0.1:0 --data-dir "$data/db" >"$data/stdout" 2>"$log" &
pid=$!
cleanup() {
    kill -TERM "$pid" 2>/dev/null || true
    wait "$pid" 2>/dev/null || true
    rm -rf "$data"
}
trap cleanup EXIT

addr=""
for _ in $(seq 1 300); do
    addr="$(sed -n 's#^vlmfuse listening on \(http://.*\)$#\1#p' "$data/stdout" | head -n1)"
    [ -n "$addr" ] && break
    if ! kill -0 "$pid" 2>/dev/null; then
        echo "vlmfuse exited early:" >&2
        cat "$log" >&2
        exit 1
    fi
    sleep 0.1
done
[ -n "$addr" ] || { echo "vlmfuse did not start" >&2; exit 1; }
echo "vlmfuse at $addr"

# /v1/infer answers 503 by design until clip ingestion lands (issue 4), which the
# not_a_server_error check would count; it is excluded here and covered by the service tests.
set +e
timeout "$time_limit" "$venv/bin/st" run "$addr/openapi.yaml" \
    --url "$addr" \
    --checks not_a_server_error,status_code_conformance,content_type_conformance,response_schema_conformance \
    --exclude-path /v1/infer \
    --max-examples "$max_examples" \
    --phases examples,coverage,fuzzing \
    --workers 1 \
    --no-color
rc=$?
set -e
if [ $rc -eq 124 ]; then
    echo "schemathesis exceeded ${time_limit}s" >&2
fi
if grep -q "panicked" "$log"; then
    echo "the server panicked:" >&2
    cat "$log" >&2
    rc=1
fi
exit $rc
