#!/usr/bin/env bash
# The README's demo: set-up, build, a synthetic yard scene with exact ground truth,
# its COLMAP database made by the real COLMAP, then every stage of colmap-lidar
# that exists, ending with the accuracy table and how to open the result.
#
#   scripts/demo.sh [OUTPUT_DIR]        (default: demo-output)
#   SCENE=room IMAGES=24 scripts/demo.sh
set -euo pipefail
cd "$(dirname "$0")/.."
root=$(pwd)
out=${1:-demo-output}
scene=${SCENE:-yard}
images=${IMAGES:-24}
mkdir -p "$out"
out=$(cd "$out" && pwd)

step() { printf '\n==> %s\n' "$*"; }

step "set-up (system packages)"
scripts/setup.sh
[ -d "$HOME/.cargo/bin" ] && export PATH="$HOME/.cargo/bin:$PATH"
export QT_QPA_PLATFORM=offscreen

step "build (release)"
cargo build --release --locked
bin="$root/target/release/colmap-lidar"
if [ -n "${CARGO_TARGET_DIR:-}" ]; then bin="$CARGO_TARGET_DIR/release/colmap-lidar"; fi

step "synthetic scene '$scene' ($images images) -> $out/scene"
"$bin" synth --scene "$scene" --images "$images" --output "$out/scene" --seed 1

step "COLMAP database (feature_extractor + exhaustive_matcher, CPU)"
db=$(scripts/make_database.sh "$out/scene" | tail -n 1)
echo "database: $db"

step "inspect the database"
"$bin" inspect --database "$db"

step "map: structure-from-motion inside the LiDAR map"
init_pose=$(awk '$1 == "perturbed:" {print $2}' "$out/scene/init_pose.txt")
"$bin" map --database "$db" --lidar "$out/scene/lidar.ply" \
  --init-image frame_0000.jpg --init-pose "$init_pose" --output "$out/sparse/0" \
  --image-path "$out/scene/images"

step "evaluate against ground truth (no alignment: poses must already be in the map frame)"
"$bin" evaluate --model "$out/sparse/0" --reference "$out/scene/gt" --align none

step "figures of the run (SVG)"
"$bin" plot "$out/sparse/0" --output "$out/figures"

step "the LiDAR map coloured by the photos (PLY)"
"$bin" colour-map --lidar "$out/scene/lidar.ply" --model "$out/sparse/0" \
  --image-path "$out/scene/images" --output "$out/map_rgb.ply"

step "the map's metric depth at every pixel of every image (16-bit PNG, millimetres)"
"$bin" depth-maps --lidar "$out/scene/lidar.ply" --model "$out/sparse/0" \
  --output "$out/depth_maps"

step "done"
cat <<MSG
Model (map frame, metres): $out/sparse/0   (report: $out/sparse/0/report.json)
Figures (planes, point-to-plane distances, reprojection errors per solve): $out/figures
Coloured map (any point-cloud viewer): $out/map_rgb.ply
Depth maps (for depth-supervised splatting or NeRF): $out/depth_maps
Open it in COLMAP:
  colmap gui --import_path $out/sparse/0 --database_path $db --image_path $out/scene/images
MSG
