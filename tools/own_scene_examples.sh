#!/usr/bin/env bash
# The figures of docs/testbed.md, "The example scenes, measured", for the two example scenes that towngen
# did not make:
# scenes/examples/campus.xml (written as MJCF) and scenes/examples/village.xml (imported from a mesh
# with `simbed import-scene`). For each: a mapping drive (one lap of its loop, OS1-64, no actors),
# the map (every 2nd scan), its quality against the scene's true surface (`simbed export-mesh`), a test
# drive (the loop the other way round, other parked cars where the scene has variants, 6 moving actors),
# then global localization from 5 start points (100 frames each). Resumable: finished steps are skipped.
#
#   bash tools/own_scene_examples.sh OUT        # e.g. /work/data/own_scenes
#   python tools/own_scene_table.py OUT         # the table
set -euo pipefail
REPO=$(cd "$(dirname "$0")/.." && pwd)
OUT=${1:-/work/data/own_scenes}
mkdir -p "$OUT"
EX="$REPO/scenes/examples"
printf "scans:\n  every_nth: 2\n" > "$OUT/every2.yaml"

run_scene() {
  local name=$1 scene=$2 map_route=$3 test_route=$4 map_frames=$5 variant=$6
  local d="$OUT/$name"
  mkdir -p "$d"
  [ -e "$d/map_run/meta.yaml" ] && grep -q "complete: true" "$d/map_run/meta.yaml" || \
    simbed record --scene "$scene" --route "$map_route" --loop --frames "$map_frames" --sensor os1-64 \
      --seed 1 --out "$d/map_run" --overwrite
  [ -e "$d/map/map.yaml" ] || rangemcl build-map "$d/map_run" --out "$d/map" --config "$OUT/every2.yaml" --overwrite
  [ -e "$d/truth.ply" ] || simbed export-mesh --scene "$scene" --out "$d/truth.ply"
  [ -e "$d/quality.json" ] || rangemcl map-quality "$d/map" --truth "$d/truth.ply" --reference "$d/map_run" \
    --json "$d/quality.json"
  [ -e "$d/test_run/meta.yaml" ] && grep -q "complete: true" "$d/test_run/meta.yaml" || \
    simbed record --scene "$scene" --route "$test_route" --loop --frames 500 --sensor os1-64 \
      --variant "$variant" --actors 6 --seed 7 --out "$d/test_run" --overwrite
  for start in 0 100 200 300 400; do
    [ -e "$d/loc_$start/summary.json" ] || rangemcl localize "$d/test_run" --map "$d/map" --out "$d/loc_$start" \
      --first-frame "$start" --frames 100 --seed 0 --overwrite
  done
}

run_scene campus "$EX/campus.xml" "$EX/campus_mapping.txt" "$EX/campus_test.txt" 650 1
run_scene village "$EX/village.xml" "$EX/village_route.txt" "$EX/village_test.txt" 700 0
echo "own_scene_examples: done ($OUT)"
