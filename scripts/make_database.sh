#!/usr/bin/env bash
# Runs Debian's COLMAP (CPU, headless) on a synthetic scene folder written by
# `colmap-lidar synth`: feature_extractor with the true camera of gt/cameras.txt
# (single camera), then exhaustive_matcher (MATCHER=sequential: sequential_matcher
# as for a video: image i with i + 1..OVERLAP in name order and, COLMAP's default
# quadratic overlap, i + 2^k for k < OVERLAP). Prints the database path.
#
# usage: scripts/make_database.sh SCENE_DIR [DATABASE] 
# env:   MAX_NUM_FEATURES (default 8192), NUM_THREADS (default 2), COLMAP (default colmap),
#        MATCHER (exhaustive|sequential, default exhaustive), OVERLAP (default 10)
set -euo pipefail
scene=${1:?usage: make_database.sh SCENE_DIR [DATABASE]}
db=${2:-$scene/database.db}
colmap=${COLMAP:-colmap}
command -v "$colmap" >/dev/null || { echo "error: '$colmap' not found (install Debian's colmap)" >&2; exit 2; }
[ -d "$scene/images" ] || { echo "error: $scene/images is not a folder" >&2; exit 2; }
cam=$(grep -v '^#' "$scene/gt/cameras.txt" | awk 'NF>=5 {printf "%s ", $2; for (i=5;i<=NF;i++) printf "%s%s", $i, (i<NF?",":""); print ""; exit}')
model=${cam%% *}
params=${cam#* }
rm -f "$db" "$db-wal" "$db-shm"
export QT_QPA_PLATFORM=offscreen
log=$(mktemp)
trap 'rm -f "$log"' EXIT
# COLMAP 3.8's matchers can deadlock in their destructor after all work is
# written: a step that printed its final "Elapsed time" line and still runs
# 20 s later is killed and counts as done.
run() {
  "$colmap" "$@" >"$log" 2>&1 &
  local pid=$! waited=0
  while kill -0 "$pid" 2>/dev/null; do
    if grep -q "Elapsed time" "$log"; then
      waited=$((waited + 1))
      if [ "$waited" -gt 80 ]; then
        echo "warning: colmap $1 finished but did not exit (known COLMAP 3.8 shutdown hang); killed it" >&2
        kill "$pid" 2>/dev/null || true
        wait "$pid" 2>/dev/null || true
        return 0
      fi
    fi
    sleep 0.25
  done
  if ! wait "$pid"; then
    echo "error: colmap $1 failed; last lines:" >&2
    tail -n 25 "$log" >&2
    exit 1
  fi
}
run feature_extractor --database_path "$db" --image_path "$scene/images" \
  --ImageReader.single_camera 1 --ImageReader.camera_model "$model" --ImageReader.camera_params "$params" \
  --SiftExtraction.use_gpu 0 --SiftExtraction.num_threads "${NUM_THREADS:-2}" \
  --SiftExtraction.max_num_features "${MAX_NUM_FEATURES:-8192}"
case "${MATCHER:-exhaustive}" in
  exhaustive)
    run exhaustive_matcher --database_path "$db" --SiftMatching.use_gpu 0 --SiftMatching.num_threads "${NUM_THREADS:-2}" ;;
  sequential)
    run sequential_matcher --database_path "$db" --SiftMatching.use_gpu 0 --SiftMatching.num_threads "${NUM_THREADS:-2}" \
      --SequentialMatching.overlap "${OVERLAP:-10}" --SequentialMatching.loop_detection 0 ;;
  *) echo "error: MATCHER must be exhaustive or sequential, got '$MATCHER'" >&2; exit 2 ;;
esac
echo "$db"
