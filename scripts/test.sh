#!/usr/bin/env bash
# The README's test command: set-up, then every test (unit and end-to-end).
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh
[ -d "$HOME/.cargo/bin" ] && export PATH="$HOME/.cargo/bin:$PATH"
export QT_QPA_PLATFORM=offscreen
cargo test --locked "$@"
