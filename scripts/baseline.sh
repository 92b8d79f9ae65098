#!/usr/bin/env bash
# Plain COLMAP baseline: runs `colmap mapper` on a database and evaluates the
# largest reconstruction against the ground truth with --align sim3 (best case
# for scale-free SfM) and --align none (what a map-frame tool must beat).
#
# usage: scripts/baseline.sh DB IMAGES GT OUTDIR
# env:   COLMAP (default colmap), COLMAP_LIDAR (default: colmap-lidar on PATH,
#        else target/release/colmap-lidar), NUM_THREADS (default 2)
# writes: OUTDIR/sparse/N (COLMAP models), OUTDIR/eval_sim3.{txt,json}, OUTDIR/eval_none.{txt,json}
set -euo pipefail
db=${1:?usage: baseline.sh DB IMAGES GT OUTDIR}
images=${2:?}
gt=${3:?}
out=${4:?}
colmap=${COLMAP:-colmap}
here=$(cd "$(dirname "$0")/.." && pwd)
tool=${COLMAP_LIDAR:-$(command -v colmap-lidar || echo "$here/target/release/colmap-lidar")}
command -v "$colmap" >/dev/null || { echo "error: '$colmap' not found" >&2; exit 2; }
[ -x "$tool" ] || { echo "error: colmap-lidar not found at $tool (cargo build --release, or set COLMAP_LIDAR)" >&2; exit 2; }
mkdir -p "$out/sparse"
rm -rf "$out"/sparse/*
start=$(date +%s)
if ! "$colmap" mapper --database_path "$db" --image_path "$images" --output_path "$out/sparse" \
    --Mapper.num_threads "${NUM_THREADS:-2}" >"$out/mapper.log" 2>&1; then
  echo "error: colmap mapper failed; last lines:" >&2
  tail -n 25 "$out/mapper.log" >&2
  exit 1
fi
echo "mapper: $(( $(date +%s) - start )) s"
# The largest model (most registered images).
best=""; best_n=-1
for m in "$out"/sparse/*/; do
  [ -f "$m/images.bin" ] || continue
  n=$(od -An -t u8 -N 8 "$m/images.bin" | tr -d ' ')
  echo "model $m: $n images"
  if [ "$n" -gt "$best_n" ]; then best=$m; best_n=$n; fi
done
[ -n "$best" ] || { echo "error: colmap mapper produced no model (see $out/mapper.log)" >&2; exit 1; }
for align in sim3 none; do
  echo "== align $align ($best)"
  "$tool" evaluate --model "$best" --reference "$gt" --align "$align" --json "$out/eval_$align.json" | tee "$out/eval_$align.txt"
done
