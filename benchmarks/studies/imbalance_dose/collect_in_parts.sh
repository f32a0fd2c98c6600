#!/bin/bash
# Run a study's collection in parts, one `--until` target after another, each part a clean pause, so that the end of a
# session (or a kill) costs at most one part. A part starts only if it can end before the deadline, judged by the pace
# of the last part (PACE: seconds per part before the first one ends; default 1500).
#
#   benchmarks/studies/imbalance_dose/collect_in_parts.sh PRESET OUTPUT SEED DEADLINE TARGET...
#
#   PRESET     the experiments preset (e.g. dose_cheetah_hip)
#   OUTPUT     the study directory (--output of `python -m sb3_lifelong.experiments run`)
#   SEED       the seed
#   DEADLINE   when the last part must have ended, as `date -d` reads it (e.g. "2026-11-26 07:00")
#   TARGET     environment steps at which to pause, in order (e.g. 475000 500000 525000)
#
# Environment: STUDY_TREE, a checkout to run the collection from (PYTHONPATH; default: the installed package);
# WAIT_PID, a process to wait for first (e.g. a part already running); LOGS, where each part's log goes (default:
# OUTPUT). Each part runs with one torch thread.
set -u
preset=$1; output=$2; seed=$3; deadline=$(date -d "$4" +%s); shift 4
logs=${LOGS:-$output}
mkdir -p "$logs"
if [ -n "${WAIT_PID:-}" ]; then
  while kill -0 "$WAIT_PID" 2>/dev/null; do sleep 20; done
fi
pace=${PACE:-1500}
for target in "$@"; do
  now=$(date +%s)
  if [ $((now + pace * 12 / 10)) -gt "$deadline" ]; then
    echo "$(date -u) seed $seed: not starting the part to $target (last pace $pace s, deadline $(date -u -d @"$deadline"))"
    break
  fi
  OMP_NUM_THREADS=1 PYTHONPATH=${STUDY_TREE:-${PYTHONPATH:-}} python -m sb3_lifelong.experiments run --preset "$preset" \
    --seed "$seed" --output "$output" --until "$target" > "$logs/seed_${seed}_to_${target}.log" 2>&1 \
    || { echo "$(date -u) seed $seed: the part to $target failed (see $logs/seed_${seed}_to_${target}.log)"; exit 1; }
  pace=$(( $(date +%s) - now ))
  echo "$(date -u) seed $seed: paused at $target after $pace s"
done
