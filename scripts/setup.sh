#!/usr/bin/env bash
# Installs what a fresh Debian 12 machine lacks to build and test colmap-lidar.
# Idempotent: installs only missing packages. Needs root (or sudo) for apt.
set -euo pipefail

packages=(
  build-essential pkg-config     # C/C++ toolchain for the Ceres bridge and bundled SQLite
  libceres-dev libeigen3-dev libgoogle-glog-dev libgflags-dev  # the solver
  colmap                         # makes the databases we read; the tests run it
)

missing=()
for p in "${packages[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done

if ((${#missing[@]})); then
  echo "setup: installing ${missing[*]}"
  sudo=""
  if [ "$(id -u)" -ne 0 ]; then sudo="sudo"; fi
  export DEBIAN_FRONTEND=noninteractive
  $sudo apt-get update -qq
  $sudo apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
else
  echo "setup: system packages present"
fi

if ! command -v cargo >/dev/null 2>&1 && [ -x "$HOME/.cargo/bin/cargo" ]; then
  export PATH="$HOME/.cargo/bin:$PATH"
fi
if ! command -v cargo >/dev/null 2>&1; then
  echo "setup: cargo not found; install the Rust toolchain (rustup) first" >&2
  exit 1
fi
