#!/usr/bin/env bash
# Map load + prepare benchmark (issue targets, 2-core machine): a synthetic
# 20-million-point building-like cloud (binary PLY, double x/y/z at UTM-like
# coordinates, no normals) is
#   1. loaded and indexed  (target: < 15 s, peak RSS < 1.5 GB), then queried
#      (nearest neighbours a second on one core, target > 2 M/s),
#   2. prepared with 3 cm voxels (the default above 20 M points; normals
#      r = 0.15 m),
#   3. prepared without downsampling (a normal for every one of the 20 M
#      points; target < 60 s).
# Times and peak memory come from /usr/bin/time -v.
#
# Usage: scripts/bench_map.sh [POINTS]   (env: BIN=path/to/colmap-lidar to
# skip the release build, WORK=dir for the files, KEEP=1 to keep them)
set -euo pipefail
cd "$(dirname "$0")/.."
POINTS=${1:-20000000}
if [[ -z "${BIN:-}" ]]; then
    cargo build --release --bin colmap-lidar
    BIN=${CARGO_TARGET_DIR:-target}/release/colmap-lidar
fi
WORK=${WORK:-$(mktemp -d -t bench_map.XXXXXX)}
mkdir -p "$WORK"
[[ -n "${KEEP:-}" ]] || trap 'rm -rf "$WORK"' EXIT
RAW="$WORK/building_${POINTS}.ply"

timed() {
    local label=$1
    shift
    /usr/bin/time -v "$@" 2>"$WORK/time.txt" | sed 's/^/    /'
    local wall rss
    wall=$(grep "Elapsed (wall clock)" "$WORK/time.txt" | awk '{print $NF}')
    rss=$(grep "Maximum resident set size" "$WORK/time.txt" | awk '{print $NF}')
    user=$(grep "User time" "$WORK/time.txt" | awk '{print $NF}')
    printf '%-34s wall %8s  user %7s s  peak RSS %6d MB\n' "$label" "$wall" "$user" $((rss / 1024))
}

echo "load: $(uptime)"
echo "== generating $POINTS points into $RAW"
"$BIN" bench-map generate --output "$RAW" --points "$POINTS"
ls -l "$RAW"
echo "== load + index (nearest-neighbour index and frustum grid; target < 15 s, < 1.5 GB)"
timed "load + index" "$BIN" bench-map load --input "$RAW" --index
echo "== nearest-neighbour queries on one core (generated map of $POINTS points; target > 2 M/s)"
"$BIN" bench-map nn --points "$POINTS" | sed 's/^/    /'
echo "== load only"
timed "load" "$BIN" bench-map load --input "$RAW"
echo "== prepare-map --voxel 0.03 (the default above 20 M points; --normal-radius 0.15)"
timed "prepare-map --voxel 0.03" "$BIN" prepare-map --input "$RAW" --output "$WORK/map_default.ply" --voxel 0.03
echo "== prepare-map --voxel 0 (normals for every point)"
timed "prepare-map --voxel 0" "$BIN" prepare-map --input "$RAW" --output "$WORK/map_full.ply" --voxel 0
echo "load: $(uptime)"
