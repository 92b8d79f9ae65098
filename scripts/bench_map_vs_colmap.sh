#!/usr/bin/env bash
# Times `colmap-lidar map` and `colmap mapper` on the same database in the same
# run and prints the ratio. With a scene folder written by `colmap-lidar synth`
# (database.db, lidar.ply, init_pose.txt, images/, gt/), also evaluates both
# against the ground truth when `colmap-lidar evaluate` is available.
#
# usage: scripts/bench_map_vs_colmap.sh SCENE_DIR [OUT_DIR]
#   SCENE_DIR holds database.db (scripts/make_database.sh), lidar.ply,
#   init_pose.txt and images/.
# env:   COLMAP (default colmap), COLMAP_LIDAR (default: colmap-lidar on PATH,
#        else target/release/colmap-lidar), NUM_THREADS for colmap mapper
#        (default 2), INIT_IMAGE (default frame_0000.jpg), POSE (exact|perturbed,
#        default exact), INIT_POSE (x,y,z,roll,pitch,yaw in degrees: this pose
#        instead, e.g. a rough one with MAP_ARGS="--init-search 2,30"),
#        MAP_ARGS (extra arguments for colmap-lidar map),
#        ABLATION (default 1: also run map --no-lidar-constraints).
set -euo pipefail
scene=${1:?usage: bench_map_vs_colmap.sh SCENE_DIR [OUT_DIR]}
out=${2:-$(mktemp -d)}
colmap=${COLMAP:-colmap}
here=$(cd "$(dirname "$0")/.." && pwd)
tool=${COLMAP_LIDAR:-$(command -v colmap-lidar || echo "$here/target/release/colmap-lidar")}
command -v "$colmap" >/dev/null || { echo "error: '$colmap' not found" >&2; exit 2; }
[ -x "$tool" ] || { echo "error: colmap-lidar not found at $tool (cargo build --release, or set COLMAP_LIDAR)" >&2; exit 2; }
db=$scene/database.db
[ -f "$db" ] || { echo "error: no database at $db (run scripts/make_database.sh $scene)" >&2; exit 2; }
pose_key=${POSE:-exact}
pose=${INIT_POSE:-$(sed -n "s/^$pose_key: *//p" "$scene/init_pose.txt")}
[ -n "$pose" ] || { echo "error: no '$pose_key:' line in $scene/init_pose.txt" >&2; exit 2; }
mkdir -p "$out"

now() { date +%s.%N; }

echo "== colmap-lidar map ($scene)"
t0=$(now)
# Both tools read the images to colour the points (colmap mapper always does).
# shellcheck disable=SC2086
if ! "$tool" map --database "$db" --lidar "$scene/lidar.ply" --output "$out/map" \
    --image-path "$scene/images" \
    --init-image "${INIT_IMAGE:-frame_0000.jpg}" --init-pose "$pose" ${MAP_ARGS:-} 2>"$out/map.log"; then
  echo "error: colmap-lidar map failed; last lines:" >&2
  tail -n 5 "$out/map.log" >&2
  exit 1
fi
t1=$(now)
ours=$(echo "$t1 - $t0" | bc -l)

echo "== colmap mapper"
rm -rf "$out/colmap" && mkdir -p "$out/colmap"
t0=$(now)
if ! "$colmap" mapper --database_path "$db" --image_path "$scene/images" --output_path "$out/colmap" \
    --Mapper.num_threads "${NUM_THREADS:-2}" >"$out/colmap.log" 2>&1; then
  echo "error: colmap mapper failed; last lines:" >&2
  tail -n 25 "$out/colmap.log" >&2
  exit 1
fi
t1=$(now)
theirs=$(echo "$t1 - $t0" | bc -l)

printf 'colmap-lidar map: %.1f s\ncolmap mapper:    %.1f s\nratio (ours / colmap): %.2f\n' \
  "$ours" "$theirs" "$(echo "$ours / $theirs" | bc -l)"

if [ -d "$scene/gt" ] && "$tool" evaluate --help >/dev/null 2>&1; then
  echo "== evaluation of colmap-lidar map (no alignment)"
  "$tool" evaluate --model "$out/map" --reference "$scene/gt" --align none || true
  for m in "$out"/colmap/*/; do
    [ -f "$m/images.bin" ] || continue
    echo "== evaluation of colmap mapper $m (Sim3 alignment)"
    "$tool" evaluate --model "$m" --reference "$scene/gt" --align sim3 || true
  done
fi
if [ -n "${ABLATION:-1}" ] && [ "${ABLATION:-1}" != 0 ]; then
  echo "== ablation: colmap-lidar map --no-lidar-constraints (the map only initialises)"
  # shellcheck disable=SC2086
  "$tool" map --database "$db" --lidar "$scene/lidar.ply" --output "$out/ablation" \
    --init-image "${INIT_IMAGE:-frame_0000.jpg}" --init-pose "$pose" --no-lidar-constraints ${MAP_ARGS:-} 2>"$out/ablation.log" \
    || echo "the ablation failed (see $out/ablation.log)" >&2
  if [ -d "$out/ablation" ] && [ -d "$scene/gt" ]; then
    "$tool" evaluate --model "$out/ablation" --reference "$scene/gt" --align none || true
  fi
fi

# Where the time of `map` goes (report.json: stages, Ceres and association time per solve kind).
if command -v python3 >/dev/null; then
  python3 - "$out/map/report.json" <<'PY'
import json, sys
r = json.load(open(sys.argv[1]))
print("== where the time of colmap-lidar map goes")
for s in r["stages"]:
    print(f"  stage {s['name']:<28} {s['time_s']:7.2f} s")
parts = ["build_s", "preprocessor_s", "residual_s", "jacobian_s", "linear_solver_s"]
kinds = {}
for s in r["solves"]:
    k = kinds.setdefault(s["kind"], {"n": 0, "iterations": 0, "wall": 0.0, "ceres": 0.0, "assoc": 0.0,
                                     **{p: 0.0 for p in parts}})
    k["n"] += 1
    k["iterations"] += s["iterations"]
    k["wall"] += s.get("wall_s", 0.0)
    k["ceres"] += s["time_s"]
    k["assoc"] += s.get("association_time_s", 0.0)
    for p in parts:
        k[p] += s.get("solver_times", {}).get(p, 0.0)
for kind, k in kinds.items():
    print(f"  {kind:<13} solves {k['n']:4d} ({k['iterations']} iterations): wall {k['wall']:7.2f} s, "
          f"Ceres {k['ceres']:7.2f} s (preprocessing {k['preprocessor_s']:.2f}, residuals "
          f"{k['residual_s']:.2f}, Jacobians {k['jacobian_s']:.2f}, linear solver "
          f"{k['linear_solver_s']:.2f}), building the problem {k['build_s']:.2f} s, "
          f"association {k['assoc']:6.2f} s")
search = r.get("init_search")
if search:
    print(f"  --init-search: run without the map's planes {search['plain_run_s']:.2f} s, search "
          f"{search['search_s']:.2f} s ({search['placements']} placements), "
          f"{len(search['contenders_on_map'])} placement(s) mapped in full (the stages above: the kept one)")
PY
fi
echo "outputs in $out"
