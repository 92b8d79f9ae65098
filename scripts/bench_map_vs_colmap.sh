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
#        ABLATION (default 1: also run map --no-lidar-constraints),
#        REPEAT (default 1: time each tool this many times, alternating which
#        goes first, and print the median ratio; later models of ours must be
#        byte-identical to the first).
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

# One timed run of a tool into the folder $1, its log in $2; prints the seconds.
run_ours() {
  local dest=$1 log=$2 t0 t1
  t0=$(now)
  # Both tools read the images to colour the points (colmap mapper always does).
  # shellcheck disable=SC2086
  if ! "$tool" map --database "$db" --lidar "$scene/lidar.ply" --output "$dest" \
      --image-path "$scene/images" \
      --init-image "${INIT_IMAGE:-frame_0000.jpg}" --init-pose "$pose" ${MAP_ARGS:-} >&2 2>"$log"; then
    echo "error: colmap-lidar map failed; last lines:" >&2
    tail -n 5 "$log" >&2
    exit 1
  fi
  t1=$(now)
  echo "$t1 - $t0" | bc -l
}
run_colmap() {
  local dest=$1 log=$2 t0 t1
  rm -rf "$dest" && mkdir -p "$dest"
  t0=$(now)
  if ! "$colmap" mapper --database_path "$db" --image_path "$scene/images" --output_path "$dest" \
      --Mapper.num_threads "${NUM_THREADS:-2}" >"$log" 2>&1; then
    echo "error: colmap mapper failed; last lines:" >&2
    tail -n 25 "$log" >&2
    exit 1
  fi
  t1=$(now)
  echo "$t1 - $t0" | bc -l
}

# Both tools read the same files: read them once first, so that neither pays
# for a cold file cache (6.5 s of a 95 s run on the 100-image corridor).
cat "$db" "$scene/lidar.ply" >/dev/null
if [ -d "$scene/images" ]; then
  find "$scene/images" -type f -exec cat {} + >/dev/null
fi

# REPEAT=N times each tool N times, alternating which goes first (times on a
# shared or virtual machine vary by a quarter from run to run), and prints
# each pair's ratio and their median. The first pair's outputs are kept and
# evaluated; every later model of ours must be byte-identical to the first.
repeat=${REPEAT:-1}
[[ "$repeat" =~ ^[1-9][0-9]*$ ]] || { echo "error: REPEAT must be a positive integer, not '$repeat'" >&2; exit 2; }
ratios=()
for ((i = 1; i <= repeat; i++)); do
  if ((i == 1)); then
    map_out=$out/map map_log=$out/map.log col_out=$out/colmap col_log=$out/colmap.log
  else
    map_out=$out/map.$i map_log=$out/map.$i.log col_out=$out/colmap.$i col_log=$out/colmap.$i.log
  fi
  tag=""
  ((repeat == 1)) || tag=" [$i/$repeat]"
  if ((i % 2 == 1)); then
    echo "== colmap-lidar map ($scene)$tag"
    ours=$(run_ours "$map_out" "$map_log")
    echo "== colmap mapper$tag"
    theirs=$(run_colmap "$col_out" "$col_log")
  else
    echo "== colmap mapper$tag"
    theirs=$(run_colmap "$col_out" "$col_log")
    echo "== colmap-lidar map ($scene)$tag"
    ours=$(run_ours "$map_out" "$map_log")
  fi
  ratio=$(echo "$ours / $theirs" | bc -l)
  ratios+=("$ratio")
  printf 'colmap-lidar map: %.1f s\ncolmap mapper:    %.1f s\nratio (ours / colmap): %.2f\n' \
    "$ours" "$theirs" "$ratio"
  if ((i > 1)); then
    for f in cameras images points3D; do
      if ! cmp -s "$out/map/$f.txt" "$map_out/$f.txt" && ! cmp -s "$out/map/$f.bin" "$map_out/$f.bin"; then
        echo "error: run $i's model differs from the first ($f; kept in $map_out)" >&2
        exit 1
      fi
    done
    rm -rf "$map_out" "$col_out"
  fi
done
if ((repeat > 1)); then
  printf 'ratios: %s\nmedian ratio (ours / colmap) over %d pairs: %.2f\n' \
    "$(printf '%.2f ' "${ratios[@]}")" "$repeat" \
    "$(printf '%s\n' "${ratios[@]}" | sort -g | awk '{a[NR] = $1} END {print (NR % 2) ? a[(NR + 1) / 2] : (a[NR / 2] + a[NR / 2 + 1]) / 2}')"
fi

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
