#!/usr/bin/env bash
# Goal-task training variants side by side on one GPU (each gets 12 % of its memory).
export XLA_PYTHON_CLIENT_MEM_FRACTION=0.12 PYTHONUNBUFFERED=1
out=${OUT:-/tmp}
run() { name=$1; shift; python benchmarks/time_to_solve_goal.py --preset gpu --eval-every 2 \
  --max-seconds ${MAXS:-90} --json $out/goal_$name.json --set randomize.families=all "$@" \
  > $out/goal_$name.log 2>&1 & }
run hist0
run hist2 --set task.history=2
run hist4 --set task.history=4
run hist8 --set task.history=8
wait
for f in $out/goal_*.log; do echo "== $f"; grep -v "^{" $f | tail -n 3; python - $f <<'PY'
import json,sys
rows=[json.loads(l) for l in open(sys.argv[1]) if l.startswith("{")]
for r in rows[-6:]: print(r["env_steps"], r["train_s"], round(r["train_success"],3), round(r["success_rate"],3), round(r["spl"],3), r["families"])
PY
done
