#!/usr/bin/env bash
# Makes the toolchain that rust-toolchain.toml pins usable without a download. Run
# by scripts/test and scripts/run (`bash scripts/toolchain.sh`) before their first cargo command.
# Idempotent.
#
# rustup installs the pinned channel on first use when it lacks it, which needs the network.
# Where rustup already has a stable toolchain of exactly the pinned version (a machine set up with
# `rustup default stable` at that release), this registers it under the pinned name instead: a
# symlink in rustup's toolchains directory, which is what an install of that name looks like to
# rustup (`rustup toolchain link` refuses names that look like releases). Nothing happens when the
# pinned toolchain is installed already, when rustup is absent, or when stable is another version
# (rustup then installs the pinned one as usual, or says why it cannot).
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
want="$(sed -n 's/^channel *= *"\(.*\)".*/\1/p' "$root/rust-toolchain.toml")"
if [ -z "$want" ] || ! command -v rustup >/dev/null 2>&1; then
  exit 0
fi
# `+stable` overrides the file, so these never trigger an install of the pinned channel.
if ! rustup toolchain list | grep -q "^${want}-"; then
  have="$(rustc +stable --version 2>/dev/null | awk '{print $2}')" || have=""
  if [ "$have" = "$want" ]; then
    host="$(rustc +stable -vV | sed -n 's/^host: //p')"
    dir="${RUSTUP_HOME:-$HOME/.rustup}/toolchains"
    ln -sfn "$(rustc +stable --print sysroot)" "$dir/${want}-${host}"
    echo "toolchain: registered stable ($have) as $want-$host (rust-toolchain.toml)" >&2
  else
    echo "toolchain: rust-toolchain.toml pins $want; stable is ${have:-absent}: rustup installs $want on first use" >&2
  fi
fi
