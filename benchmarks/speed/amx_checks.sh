#!/usr/bin/env bash
# The checks that need a CPU with native bf16 (AMX or AVX-512 BF16), as one run of under 10 minutes on a machine
# with at least 14 cores: each check one process with one torch thread, pinned to its own core, all at once.
#
#   bash benchmarks/speed/amx_checks.sh [OUTPUT_DIR]      # default benchmarks/results/speed/amx_checks
#
# It needs the package importable (installed, or PYTHONPATH=<repo>) with gymnasium[mujoco] and SB3. It prints the
# tables at the end; each check's whole output is in OUTPUT_DIR/<name>.log:
#   flags              the CPU's matrix flags and oneDNN's bf16 kernel
#   compiled_vs_eager  compiled against eager (and float64) on this CPU and torch (the tanh bug, the check)
#   test_compiled      tests/common/test_compiled.py and tests/common/test_train_dtype.py
#   student_compiled   a study student, eager against compiled
#   student_train      a study student, compiled, float32 against bf16 gradient passes (train_dtype)
#   mpo_train          MPO (N=20, LayerNorm, compiled) against SAC, float32 and bf16 gradient passes, Walker2d
#   batched[_compiled] K students' update cores one after the other against batched (bench_batched_students.py)
#   mpo_train_hopper   the same on Hopper-v5
#   crr_<dtype>_<seed> CRR on the fixed Hopper dataset, 3000 updates, its return, float32 and bf16 gradient
#                      passes, seeds 0-2
#   crr_d3rlpy_compiled  the compiled CRR against d3rlpy 2.8.1, interleaved (bench_crr.py; where d3rlpy imports)
#   crr_return_<seed>  crr_train_dtype_return.py's protocol (5000 updates, float32 against native bf16), seeds 0-4,
#                      then its verdict over them (crr_return/bfloat16.md)
#
# CHECK_SECONDS (default 540) is each check's time limit; a few seconds make a dry run that only starts each one.
# ONLY="name name ..." runs only those checks (crr_return runs all five seeds; crr_d3rlpy_compiled and the batched
# ones by their names): a second visit to a machine need not repeat the first one's checks.
set -uo pipefail
cd "$(dirname "$0")/.."
OUT=${1:-benchmarks/results/speed/amx_checks}
mkdir -p "$OUT"
export OMP_NUM_THREADS=1 MKL_NUM_THREADS=1 PYTHONUNBUFFERED=1
PY=${PYTHON:-python}
seconds=${CHECK_SECONDS:-540}
cores=$(nproc)
core=0
wanted() {  # wanted NAME: whether ONLY (when set) names this check
    [ -z "${ONLY:-}" ] || [[ " $ONLY " == *" ${1%_[0-9]} "* ]] || [[ " $ONLY " == *" $1 "* ]]
}
run() {  # run NAME SECONDS COMMAND...: in the background, on the next core (when taskset and the core exist)
    local name=$1 seconds=$2
    shift 2
    wanted "$name" || return 0
    local pin=()
    if command -v taskset > /dev/null && [ "$core" -lt "$cores" ]; then pin=(taskset -c "$core"); fi
    core=$((core + 1))
    (timeout "$seconds" "${pin[@]}" "$@" > "$OUT/$name.log" 2>&1; echo "exit $?" >> "$OUT/$name.log") &
}
$PY -c "from sb3_lifelong.numerics.hardware import machine_description; print(machine_description())" > "$OUT/flags.log" 2>&1
run compiled_vs_eager $seconds $PY benchmarks/compiled_vs_eager.py (retired: `git show 9cccda3:benchmarks/compiled_vs_eager.py`)
run test_compiled $seconds $PY -m pytest -q -p no:cacheprovider -rs tests/common/test_compiled.py tests/common/test_train_dtype.py
run student_compiled $seconds $PY benchmarks/speed/student_anatomy.py compare --blocks 6
run student_train $seconds $PY benchmarks/speed/student_anatomy.py compare --train-dtype --compile-losses --blocks 6
run mpo_train $seconds $PY benchmarks/speed/bench_mpo_throughput.py --envs Walker2d-v5 --rounds 3 --steps 500 --num-samples 20 \
    --scoring-dtypes auto --layer-norms on --compile-losses on --train-dtypes float32 bfloat16 --threads 1 \
    --output "$OUT/mpo_throughput"
run mpo_train_hopper $seconds $PY benchmarks/speed/bench_mpo_throughput.py --envs Hopper-v5 --rounds 3 --steps 500 \
    --num-samples 20 --scoring-dtypes auto --layer-norms on --compile-losses on --train-dtypes float32 bfloat16 \
    --threads 1 --output "$OUT/mpo_throughput_hopper"
if $PY -c "import d3rlpy" > /dev/null 2>&1; then
    run crr_d3rlpy_compiled $seconds $PY benchmarks/speed/bench_crr.py --impl both --updates 1000 --eval-episodes 3 \
        --speed-rounds 3 --compile-losses --d3rlpy-python "$(command -v $PY)" --output "$OUT/crr_hopper_compiled.md"
fi
run batched $seconds $PY benchmarks/speed/bench_batched_students.py --output "$OUT/batched_students.json"
run batched_compiled $seconds $PY benchmarks/speed/bench_batched_students.py --compile --output "$OUT/batched_students_compiled.json"
for seed in 0 1 2; do
    for dtype in float32 bfloat16; do
        run "crr_${dtype}_$seed" $seconds $PY benchmarks/speed/bench_crr.py --impl ours --updates 3000 --eval-episodes 10 \
            --train-dtype $dtype --seed $seed
    done
done
for seed in 0 1 2 3 4; do
    run "crr_return_$seed" $seconds $PY benchmarks/studies/crr_train_dtype_return/crr_train_dtype_return.py --seeds $seed --other bfloat16 \
        --output "$OUT/crr_return_$seed"
done
wait
if wanted crr_return; then  # the verdict over the seeds that finished
    finished=()
    for dir in "$OUT"/crr_return_[0-4]; do [ -f "$dir/bfloat16.json" ] && finished+=("$dir"); done
    if [ ${#finished[@]} -gt 0 ]; then
        $PY benchmarks/studies/crr_train_dtype_return/crr_train_dtype_return.py --other bfloat16 --output "$OUT/crr_return" --merge "${finished[@]}" \
            > "$OUT/crr_return.log" 2>&1
    fi
fi
cat "$OUT/flags.log"
grep -h "torso\|first update\|compiled True\|compiled False" "$OUT/compiled_vs_eager.log" | head -30
grep -hE "passed|failed|SKIPPED" "$OUT/test_compiled.log" | tail -6
for name in student_compiled student_train; do echo "== $name"; grep -h "^|\|compiled update in use" "$OUT/$name.log" 2>/dev/null; done
for name in mpo_train mpo_train_hopper; do echo "== $name"; grep -h "^|" "$OUT/$name.log" 2>/dev/null | head -12; done
for name in batched batched_compiled; do echo "== $name"; grep -h "^|" "$OUT/$name.log" 2>/dev/null; done
echo "== crr_d3rlpy_compiled"; grep -h "^|\|ratio" "$OUT/crr_d3rlpy_compiled.log" 2>/dev/null | head -20
echo "== CRR on the fixed dataset (one JSON line a run: updates, seconds, return)"; grep -h '"impl"' "$OUT"/crr_*.log 2>/dev/null
echo "== crr_return"; cat "$OUT/crr_return/bfloat16.md" 2>/dev/null || tail -3 "$OUT/crr_return.log" 2>/dev/null
