#!/usr/bin/env bash
# How far off may the initial pose be? Runs `colmap-lidar map` on one scene
# from initial poses moved away from the exact one by growing amounts (0 to
# 2.2 m and 0 to 12 deg, in directions spread over the sphere) and sorts each
# run by its outcome against the ground truth: right (camera-centre median
# under RIGHT_M), failed with an error (nothing written), or wrong without an
# error (the outcome that must not happen).
#
# usage: scripts/bench_init_pose.sh SCENE_DIR [OUT_DIR]
#   SCENE_DIR is a `colmap-lidar synth` folder with database.db
#   (scripts/make_database.sh), lidar.ply, init_pose.txt and gt/.
# env:   COLMAP_LIDAR (default: colmap-lidar on PATH, else
#        target/release/colmap-lidar), INIT_IMAGE (default frame_0000.jpg),
#        RIGHT_M (default 0.01), MAP_ARGS (extra arguments for map),
#        STEPS ("metres:degrees ...", default the 17 steps below).
set -euo pipefail
scene=${1:?usage: bench_init_pose.sh SCENE_DIR [OUT_DIR]}
out=${2:-$(mktemp -d)}
here=$(cd "$(dirname "$0")/.." && pwd)
tool=${COLMAP_LIDAR:-$(command -v colmap-lidar || echo "$here/target/release/colmap-lidar")}
[ -x "$tool" ] || { echo "error: colmap-lidar not found at $tool (cargo build --release, or set COLMAP_LIDAR)" >&2; exit 2; }
for f in database.db lidar.ply init_pose.txt gt/images.txt; do
  [ -f "$scene/$f" ] || { echo "error: $scene/$f not found" >&2; exit 2; }
done
exact=$(sed -n 's/^exact: *//p' "$scene/init_pose.txt")
[ -n "$exact" ] || { echo "error: no 'exact:' line in $scene/init_pose.txt" >&2; exit 2; }
steps=${STEPS:-"0:0 0.15:1 0.3:2 0.3:6 0.45:3 0.6:4 0.6:8 0.75:5 0.9:6 0.9:8 1.1:8 1.2:9 1.4:10 1.6:10 1.8:11 2.0:12 2.2:12"}
mkdir -p "$out"

# Pose k of n: the exact pose moved by m metres along the k-th point of a
# Fibonacci sphere and turned by d degrees (roll, pitch, yaw) along another.
perturb() {
  awk -v p="$exact" -v m="$1" -v d="$2" -v k="$3" -v n="$4" '
  # Adds s times the i-th of n Fibonacci-sphere directions (turned by t) to v[o+1..o+3].
  function add(o, i, t, s,   z, r, a) {
    z = 1 - (2 * i + 1) / n; r = sqrt(1 - z * z); a = atan2(0, -1) * (3 - sqrt(5)) * i + t;
    v[o + 1] += s * r * cos(a); v[o + 2] += s * r * sin(a); v[o + 3] += s * z;
  }
  BEGIN {
    split(p, v, ",");
    add(0, k, 0, m); add(3, n - 1 - k, 1, d);
    printf "%.9f,%.9f,%.9f,%.9f,%.9f,%.9f", v[1], v[2], v[3], v[4], v[5], v[6]
  }'
}

set -- $steps
n=$#
k=0
right=0 failed=0 wrong=0
printf '%-8s %-7s %s\n' "off (m)" "(deg)" "outcome"
for step in "$@"; do
  m=${step%%:*} d=${step##*:}
  pose=$(perturb "$m" "$d" "$k" "$n")
  run="$out/pose_$k"
  k=$((k + 1))
  echo "init pose: $pose" >"$run.log"
  # shellcheck disable=SC2086
  if "$tool" map -q --database "$scene/database.db" --lidar "$scene/lidar.ply" \
      --init-image "${INIT_IMAGE:-frame_0000.jpg}" --init-pose "$pose" --output "$run" \
      ${MAP_ARGS:-} >/dev/null 2>>"$run.log"; then
    median=$("$tool" evaluate --model "$run" --reference "$scene/gt" --align none 2>&1 |
      awk '/centre error/ {print $4}' || true)
    if [ -z "$median" ]; then
      echo "error: evaluate failed on $run" >&2
      exit 1
    elif awk -v e="$median" -v t="${RIGHT_M:-0.01}" 'BEGIN {exit !(e < t)}'; then
      outcome="right, $(awk -v e="$median" 'BEGIN {printf "%.1f mm", e * 1000}') median"
      # The run from the pose failed and the search around it (the mapper's
      # fallback, bundle.fallback_search_m) found the model.
      if grep -q '"after_failure": *"' "$run/report.json"; then outcome="$outcome, after the fallback search"; fi
      right=$((right + 1))
    else
      outcome="WRONG WITHOUT AN ERROR, $(awk -v e="$median" 'BEGIN {printf "%.3f m", e}') median"
      wrong=$((wrong + 1))
    fi
  else
    error=$(grep -m1 '^error' "$run.log" || echo "error: (none in $run.log)")
    why=$(echo "$error" | grep -o 'the model does not fit the map: [0-9]* %\|the initial image ended [0-9.]* m and [0-9.]* deg' | head -1 || true)
    if echo "$error" | grep -q 'may have slid along'; then why="$why (slid along a weak direction)"; fi
    outcome="error: ${why:-${error:0:160}}"
    failed=$((failed + 1))
  fi
  printf '%-8s %-7s %s\n' "$m" "$d" "$outcome"
done
echo "right $right, failed with an error $failed, wrong without an error $wrong (of $n; runs in $out)"
