#!/usr/bin/env bash
# The town_large experiments (docs/trials.md), end to end, resumable: the map of the whole covering
# drive, the odometry sweeps on the OS1-64 and HDL-64E test drives, then the sensors and particles suites
# with this localizer and with the paper's pipeline. Hours of work on 2 cores: run it in the background,
#
#   nohup bash tools/town_large_suites.sh /work/data > /work/data/town_large.log 2>&1 &
#
# and rerun the same command after an interruption: every step that finished left a stamp in
# DATA/stamps/ and is skipped; the covering drive resumes from its last checkpoint (the test drives are
# redone whole), build-map resumes its tiles, the sweeps
# reuse their finished runs and the suites their finished trials. The code is frozen at the first run
# into DATA/src (a `git archive` of HEAD), so later edits in the work tree do not change the runs;
# delete DATA/src to run newer code (and the stamps of the steps to redo).
#
# Steps (STEPS=... limits them, e.g. STEPS="map sweeps"):
#   map       record the covering drive (os1-64, seed 1, 20,013 frames) and build the map (every 2nd scan)
#   sweeps    tools/odometry_sweep.py, tracking and after global convergence, OS1-64 and HDL-64E drives
#   sensors   the sensors suite, 5 presets x 10 starts x 100 frames, 10,000 particles
#   particles the particles suite, range model, 1,000/5,000/10,000 particles, 10 starts
#   paper     both suites again with configs/paper.yaml (paper-sensors, paper-particles: one of them);
#             each runs right after the suite it repeats
#   robustness the robustness suite with configs/fast.yaml, 5 presets x 10 starts at each realism level:
#             ideal and realistic first (its ideal level runs the sensors suite's trials: the same drives,
#             starts and seeds), then rain, dropout and fog; not in the default steps (STEPS=robustness)
set -euo pipefail
REPO=$(cd "$(dirname "$0")/.." && pwd)
DATA=${1:-/work/data}
STEPS=${STEPS:-map sweeps sensors particles paper}
mkdir -p "$DATA/stamps"
cd "$DATA"

if [ ! -d src ]; then
  mkdir -p src.tmp && git -C "$REPO" archive HEAD | tar -x -C src.tmp && mv src.tmp src
  git -C "$REPO" rev-parse HEAD > src/REVISION
fi
export PYTHONPATH="$DATA/src"
SIMBED=(python -m simbed.cli)
RANGEMCL=(python -m rangemcl.cli)
echo "town_large_suites: code $(cat src/REVISION), data $DATA, steps: $STEPS ($(date -u +%FT%TZ))"

want() { [[ " $STEPS " == *" $1 "* ]]; }
done_() { [ -e "stamps/$1" ]; }
stamp() { date -u +%FT%TZ > "stamps/$1"; echo "== $1 done $(cat "stamps/$1")"; }

SUITE=(--map large_full_map --scene town_large --drive-frames 800 --frames 100 --starts 10 --workers 2)
SENSORS=hdl-64e,hdl-32e,os1-128,mq-8,vlp-16

record_drive() {  # the suites' test drive of one sensor (route test, variant 1, 10 actors, seed 7)
  local sensor=$1 drive=drives/town_large-$1-test-v1-a10-d7-n800
  done_ "drive-$sensor" && return 0
  "${SIMBED[@]}" record --scene town_large --route test --variant 1 --actors 10 --frames 800 --seed 7 \
    --sensor "$sensor" --out "$drive" --overwrite > "drive-$sensor.log" 2>&1
  stamp "drive-$sensor"
}

if want map; then
  # the sweeps' drives are recorded on the second core while the covering drive records on the first
  if want sweeps; then (record_drive os1-64; record_drive hdl-64e) & fi
  if ! done_ record; then
    again=(--overwrite)  # an interrupted recording goes on from its last checkpoint
    [ -e large_full_run/.record_checkpoint.npz ] && again=(--resume)
    "${SIMBED[@]}" record --scene town_large --route mapping --sensor os1-64 --actors 0 --frames 25000 \
      --seed 1 --out large_full_run "${again[@]}"
    stamp record
  fi
  if ! done_ build; then
    printf "scans:\n  every_nth: 2\n" > every2.yaml
    resume=()
    [ -d large_full_map/.build ] && resume=(--resume)
    /usr/bin/time -v "${RANGEMCL[@]}" build-map large_full_run --out large_full_map --config every2.yaml \
      "${resume[@]}" 2> build_time.txt || { cat build_time.txt; exit 1; }
    tail -n 25 build_time.txt
    stamp build
  fi
fi

if want sweeps; then
  wait  # the drives recorded beside the map, if any
  record_drive os1-64
  record_drive hdl-64e
  for mode in tracking global; do
    pids=()
    for sensor in os1-64 hdl-64e; do
      done_ "sweep-$mode-$sensor" && continue
      ( python "$DATA/src/tools/odometry_sweep.py" --seq drives/town_large-$sensor-test-v1-a10-d7-n800 \
          --map large_full_map --out "sweeps/$mode-$sensor" --mode "$mode" > "sweeps-$mode-$sensor.log" 2>&1 \
        && stamp "sweep-$mode-$sensor" ) &
      pids+=($!)
    done
    for p in "${pids[@]}"; do wait "$p"; done
  done
fi

# the paper's pipeline right after each suite, so that each side-by-side table is whole as early as can be
# no stamps for the suites: they reuse their finished trials by key, and the key holds the localizer's
# version (a stamp would skip the suite of a newer version)
if want sensors; then
  "${SIMBED[@]}" trials sensors --out suites/large "${SUITE[@]}" --sensors $SENSORS
  stamp sensors
fi
if want paper || want paper-sensors; then
  "${SIMBED[@]}" trials sensors --out suites/large "${SUITE[@]}" --sensors $SENSORS \
    --config src/configs/paper.yaml
  stamp paper-sensors
fi
if want particles; then
  "${SIMBED[@]}" trials particles --out suites/large "${SUITE[@]}" --models range --counts 1000,5000,10000
  stamp particles
fi
if want paper || want paper-particles; then
  "${SIMBED[@]}" trials particles --out suites/large "${SUITE[@]}" --models range \
    --counts 1000,5000,10000 --config src/configs/paper.yaml
  stamp paper-particles
fi
if want robustness; then
  for levels in ideal,realistic rain,dropout fog; do
    "${SIMBED[@]}" trials robustness --out suites/large_robust "${SUITE[@]}" --sensors $SENSORS \
      --levels $levels --config src/configs/fast.yaml
  done
  stamp robustness
fi
echo "town_large_suites: finished $(date -u +%FT%TZ)"
