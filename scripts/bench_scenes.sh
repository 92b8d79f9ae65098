#!/usr/bin/env bash
# The accuracy table of the README and docs/guide.md: the synthetic scenes (corridor, room, yard;
# seeds 0-2; 24 images) mapped from the exact and the perturbed initial pose
# (0.3 m, 3 deg), against `colmap mapper` on the same database given the true
# similarity (the oracle). Databases are made once and kept in OUT_DIR, so a
# second call with other MAP_ARGS compares on the same data.
#
# usage: scripts/bench_scenes.sh OUT_DIR
# env:   SCENES (default "corridor room yard"), SEEDS (default "0 1 2"),
#        IMAGES (default 24), POSES (default "exact perturbed"),
#        MAP_ARGS (extra arguments for map, e.g. "--options opts.toml"),
#        SYNTH_ARGS (extra arguments for synth when a database is made; scenes
#        already in OUT_DIR are kept, so use a new OUT_DIR to change them; e.g.
#        "--offset 500000,4400000,200" or "--width 1024 --height 768"),
#        TAG (default "default": each run's folder is TAG-POSE), ORACLE (1: run
#        colmap mapper once per database, 0: skip), COLMAP_LIDAR (default:
#        colmap-lidar on PATH, else target/release/colmap-lidar), IMAGE_PATH
#        (default 1: map is given the scene's images, so it colours the points
#        and refines the keypoints on the map's planes; 0: not)
# writes: OUT_DIR/SCENE-SEED/{database.db,TAG-POSE/,oracle/}, OUT_DIR/TAG.tsv
# prints: per run the camera-centre median and p90 (mm), rotation median (deg),
#         registered share, and our median over the oracle's
set -euo pipefail
out=${1:?usage: bench_scenes.sh OUT_DIR}
here=$(cd "$(dirname "$0")/.." && pwd)
tool=${COLMAP_LIDAR:-$(command -v colmap-lidar || echo "$here/target/release/colmap-lidar")}
[ -x "$tool" ] || { echo "error: colmap-lidar not found at $tool (cargo build --release, or set COLMAP_LIDAR)" >&2; exit 2; }
scenes=${SCENES:-corridor room yard}
seeds=${SEEDS:-0 1 2}
poses=${POSES:-exact perturbed}
tag=${TAG:-default}
mkdir -p "$out"
out=$(cd "$out" && pwd)
table="$out/$tag.tsv"
printf 'scene\tseed\tpose\tregistered\tmedian_mm\tp90_mm\trot_deg\toracle_mm\tratio\ttime_s\n' >"$table"

# median_mm p90_mm rot_deg registered of an evaluate --json file.
read_eval() {
  python3 - "$1" <<'PY'
import json, sys
r = json.load(open(sys.argv[1]))
c = r["centre_error_m"]; a = r.get("rotation_error_deg") or {}
print(f'{1e3*c["median"]:.2f} {1e3*c["p90"]:.2f} {a.get("median", float("nan")):.4f} '
      f'{r.get("num_registered", "?")}/{r.get("num_reference", "?")}')
PY
}

for scene in $scenes; do
  for seed in $seeds; do
    dir="$out/$scene-$seed"
    if [ ! -f "$dir/database.db" ]; then
      echo "== $scene seed $seed: scene and database"
      rm -rf "$dir"
      # shellcheck disable=SC2086
      "$tool" synth --scene "$scene" --images "${IMAGES:-24}" --seed "$seed" --output "$dir" \
        ${SYNTH_ARGS:-} >/dev/null
      scripts_dir="$here/scripts"
      "$scripts_dir/make_database.sh" "$dir" >/dev/null
    fi
    oracle=nan
    if [ "${ORACLE:-1}" = 1 ]; then
      if [ ! -f "$dir/oracle/eval_sim3.json" ]; then
        "$here/scripts/baseline.sh" "$dir/database.db" "$dir/images" "$dir/gt" "$dir/oracle" >/dev/null
      fi
      oracle=$(read_eval "$dir/oracle/eval_sim3.json" | awk '{print $1}')
    fi
    for pose in $poses; do
      init=$(sed -n "s/^$pose: *//p" "$dir/init_pose.txt")
      [ -n "$init" ] || { echo "error: no '$pose:' line in $dir/init_pose.txt" >&2; exit 2; }
      run="$dir/$tag-$pose"
      rm -rf "$run"
      mkdir -p "$run"
      start=$(date +%s.%N)
      # shellcheck disable=SC2086
      images=()
      [ "${IMAGE_PATH:-1}" = 1 ] && images=(--image-path "$dir/images")
      if "$tool" map --database "$dir/database.db" --lidar "$dir/lidar.ply" \
          --init-image frame_0000.jpg --init-pose "$init" --output "$run/model" \
          "${images[@]}" ${MAP_ARGS:-} >"$run/map.log" 2>&1; then
        secs=$(awk -v a="$start" -v b="$(date +%s.%N)" 'BEGIN { print b - a }')
        "$tool" evaluate --model "$run/model" --reference "$dir/gt" --align none \
          --json "$run/eval.json" >/dev/null
        read -r med p90 rot reg < <(read_eval "$run/eval.json")
        ratio=$(python3 -c "import math,sys; o=float('$oracle'); print('nan' if math.isnan(o) else f'{$med/o:.2f}')")
      else
        secs=$(awk -v a="$start" -v b="$(date +%s.%N)" 'BEGIN { print b - a }')
        med=fail p90=- rot=- reg=- ratio=-
        echo "   $scene $seed $pose: map failed: $(tail -n 1 "$run/map.log")" >&2
      fi
      printf '%s\t%s\t%s\t%s\t%s\t%s\t%s\t%s\t%s\t%.1f\n' "$scene" "$seed" "$pose" "$reg" "$med" "$p90" "$rot" "$oracle" "$ratio" "$secs" | tee -a "$table"
    done
  done
done
python3 - "$table" <<'PY'
import sys, csv
rows = list(csv.DictReader(open(sys.argv[1]), delimiter="\t"))
ok = [r for r in rows if r["median_mm"] != "fail"]
inside = [r for r in ok if r["ratio"] not in ("nan", "-") and float(r["ratio"]) <= 1.5]
total = sum(float(r["median_mm"]) for r in ok)
print(f"runs {len(rows)}, mapped {len(ok)}, sum of medians {total:.1f} mm, "
      f"within 1.5x of the oracle {len(inside)} of {len(ok)}")
PY
