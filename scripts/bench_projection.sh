#!/usr/bin/env bash
# Benchmarks of the map index and of the projection of the map into a camera
# (numbers, not pass/fail): nearest-neighbour queries a second on one core,
# load + index time and peak memory of a 20-million-point binary PLY, and the
# time of one projection at ~8000 query pixels with ~2 million points in view.
#
# Usage: scripts/bench_projection.sh [points]   (default 20000000)
# Needs ~3 GB of free memory at the default size. Builds in release mode.
set -euo pipefail
cd "$(dirname "$0")/.."
export COLMAP_LIDAR_BENCH_POINTS="${1:-20000000}"
echo "load: $(uptime)"
cargo test --release --test tests -- --ignored --exact --nocapture --test-threads 1 \
    map::index::bench_index map::projection::bench_projection 2>&1 | grep -oE '(BENCH|panicked|error).*'
echo "load: $(uptime)"
