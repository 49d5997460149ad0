#!/usr/bin/env bash
# Installs the Debian packages vlmfuse builds and tests against (python3, pip and venv for the
# asset fetch, schemathesis and the CUDA wheels; g++, nvcc's host compiler, for the CUDA build;
# chromium for the operator page's browser test; postgresql, whose server the replica tests start
# on a loopback port with a temporary data directory, never the package's own cluster). Idempotent: it asks apt only
# for what is missing, so a second run costs a dpkg query and nothing else.
set -euo pipefail
pkgs=(pkg-config clang libclang-dev libavcodec-dev libavformat-dev libavutil-dev
      libswscale-dev libswresample-dev libavfilter-dev libavdevice-dev ffmpeg
      python3 python3-pip python3-venv g++ chromium postgresql)
missing=()
for p in "${pkgs[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
if [ ${#missing[@]} -gt 0 ]; then
  SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
  echo "setup: installing ${missing[*]}" >&2
  export DEBIAN_FRONTEND=noninteractive
  $SUDO apt-get update -qq
  $SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
fi
