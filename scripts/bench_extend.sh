#!/usr/bin/env bash
# Extending a model with new photos (`map --input-model`) against mapping
# everything again, on one database in the same run: the full run's model
# loses its last images (`colmap image_deleter`, so the input model is one
# COLMAP wrote), then `map --input-model` registers them again, with the
# model's images held (--fix-existing-images) and free. Prints wall time and
# peak memory of each run and the errors (`evaluate --align none`) over all
# images and over the re-added ones.
#
# usage: scripts/bench_extend.sh SCENE_DIR [OUT_DIR]
#   SCENE_DIR: a `colmap-lidar synth` folder with database.db
#   (scripts/make_database.sh), lidar.ply, init_pose.txt and gt/.
# env:   COLMAP (default colmap), COLMAP_LIDAR (default: colmap-lidar on PATH,
#        else target/release/colmap-lidar), KEEP (share of the images, in
#        name order, the input model keeps; default 0.75), FULL (a full run's
#        model to start from instead of running one; its time is then not
#        measured), INIT_IMAGE (default frame_0000.jpg).
set -euo pipefail
scene=${1:?usage: bench_extend.sh SCENE_DIR [OUT_DIR]}
out=${2:-$(mktemp -d)}
colmap=${COLMAP:-colmap}
here=$(cd "$(dirname "$0")/.." && pwd)
tool=${COLMAP_LIDAR:-$(command -v colmap-lidar || echo "$here/target/release/colmap-lidar")}
command -v "$colmap" >/dev/null || { echo "error: '$colmap' not found" >&2; exit 2; }
[ -x "$tool" ] || { echo "error: colmap-lidar not found at $tool (cargo build --release, or set COLMAP_LIDAR)" >&2; exit 2; }
db=$scene/database.db
[ -f "$db" ] || { echo "error: no database at $db (run scripts/make_database.sh $scene)" >&2; exit 2; }
[ -d "$scene/gt" ] || { echo "error: no ground truth at $scene/gt" >&2; exit 2; }
keep=${KEEP:-0.75}
mkdir -p "$out"

# run NAME ARGS...: colmap-lidar map into $out/NAME, its time and peak memory.
run() {
  local name=$1
  shift
  rm -rf "${out:?}/$name"
  /usr/bin/time -f "%e %M" -o "$out/$name.time" \
    "$tool" map --database "$db" --lidar "$scene/lidar.ply" --output "$out/$name" "$@" \
    >"$out/$name.out" 2>"$out/$name.log"
  read -r secs kb <"$out/$name.time"
  printf '%-14s %8.1f s %8.0f MB\n' "$name" "$secs" "$(echo "$kb / 1024" | bc -l)"
}

# errors MODEL REFERENCE: median / p90 / max centre error (mm), rotation median (deg), registered.
errors() {
  "$tool" evaluate --model "$1" --reference "$2" --align none 2>&1 | awk '
    /^registered/ { reg = $2 "/" $4 }
    /^centre error/ { c = sprintf("%.1f / %.1f / %.1f mm", $4 * 1e3, $5 * 1e3, $6 * 1e3) }
    /^rotation error/ { r = sprintf("%.4f deg", $4) }
    END { printf "%s registered, centre %s, rotation median %s", reg, c, r }'
}

if [ -n "${FULL:-}" ]; then
  full=$FULL
  echo "full run: $full (given, not timed)"
else
  pose=$(sed -n "s/^exact: *//p" "$scene/init_pose.txt")
  run full --init-image "${INIT_IMAGE:-frame_0000.jpg}" --init-pose "$pose"
  full=$out/full
fi

# The images the input model loses: the last (1 - KEEP) of them by name.
rm -rf "$out/full_txt" && mkdir -p "$out/full_txt"
"$colmap" model_converter --input_path "$full" --output_path "$out/full_txt" --output_type TXT \
  >/dev/null 2>&1
names=$(grep -v '^#' "$out/full_txt/images.txt" | awk 'NR % 2 == 1 { print $10 }' | sort)
total=$(echo "$names" | wc -l)
kept=$(printf '%.0f' "$(echo "$total * $keep" | bc -l)")
echo "$names" | tail -n +"$((kept + 1))" >"$out/removed.txt"
echo "input model: $kept of $total images (the last $((total - kept)) by name removed with colmap image_deleter)"
rm -rf "$out/input" "$out/gt_new" && mkdir -p "$out/input" "$out/gt_new"
"$colmap" image_deleter --input_path "$full" --output_path "$out/input" \
  --image_names_path "$out/removed.txt" >"$out/deleter.log" 2>&1
# The ground truth of the re-added images only (every other name deleted).
grep -v '^#' "$scene/gt/images.txt" | awk 'NR % 2 == 1 { print $10 }' |
  grep -vxF -f "$out/removed.txt" >"$out/not_removed.txt" || true
"$colmap" image_deleter --input_path "$scene/gt" --output_path "$out/gt_new" \
  --image_names_path "$out/not_removed.txt" >>"$out/deleter.log" 2>&1

run held --input-model "$out/input" --fix-existing-images
run free --input-model "$out/input"

echo "== errors (no alignment): all images; the re-added ones"
for name in full held free; do
  model=$out/$name
  [ "$name" = full ] && model=$full
  echo "$name: $(errors "$model" "$scene/gt"); new: $(errors "$model" "$out/gt_new")"
done
