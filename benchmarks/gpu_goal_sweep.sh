#!/usr/bin/env bash
# Goal-task training variants side by side on one GPU (each gets 12 % of its memory), judged by
# benchmarks/time_to_solve_goal.py; the variants share the GPU, so compare env steps, not seconds.
#   OUT=dir MAXS=120 bash benchmarks/gpu_goal_sweep.sh "base" "sample --sample" \
#       "hist16 --set task.history=16"
# Each argument: a name, then that variant's extra flags; $EXTRA are every variant's and $PRESET
# the preset (default gpu); with $GPUS set, variant i runs on GPU i mod $GPUS. Every variant trains
# in `--set randomize.families=all` (the cpu preset's own mixture too) unless its flags set the
# families again. Writes $OUT/goal_<name>.json, and the printout to $LOGS/goal_<name>.log (default
# $OUT).
export XLA_PYTHON_CLIENT_MEM_FRACTION=${MEMFRAC:-0.12} PYTHONUNBUFFERED=1
out=${OUT:-/tmp}
logs=${LOGS:-$out}
i=0
for variant in "$@"; do
  read -r name flags <<<"$variant"
  if [ -n "${GPUS:-}" ]; then export CUDA_VISIBLE_DEVICES=$((i % GPUS)); fi
  i=$((i + 1))
  # shellcheck disable=SC2086
  python benchmarks/time_to_solve_goal.py --preset "${PRESET:-gpu}" --eval-every "${EVERY:-2}" \
    --max-seconds "${MAXS:-90}" --json "$out/goal_$name.json" --set randomize.families=all \
    ${EXTRA:-} $flags >"$logs/goal_$name.log" 2>&1 &
done
wait
for variant in "$@"; do
  read -r name _ <<<"$variant"
  echo "== $name"; grep -v "^{" "$logs/goal_$name.log" | tail -n 2
  python - "$logs/goal_$name.log" <<'PY'
import json, sys
rows = [json.loads(line) for line in open(sys.argv[1]) if line.startswith("{")]
for r in rows[-4:]:
    print(r["env_steps"], r["train_s"], round(r["train_success"], 3), round(r["success_rate"], 3),
          round(r["spl"], 3), r.get("collision_rate"), r["families"])
PY
done
