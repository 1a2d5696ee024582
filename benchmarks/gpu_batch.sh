#!/usr/bin/env bash
# The H200 measurements of one version, one job per GPU of a 4-GPU host, each under a time limit.
# Usage (repository root): OUT=results_dir bash benchmarks/gpu_batch.sh
export PYTHONUNBUFFERED=1
out=${OUT:?set OUT}
limit=${LIMIT:-540}
job() { gpu=$1; name=$2; shift 2; ( export CUDA_VISIBLE_DEVICES=$gpu; timeout $limit bash -c "$*" \
  > $out/$name.log 2>&1; echo "exit $?" >> $out/$name.log ) & }
job 0 throughput "python benchmarks/throughput.py --num-envs 65536 --steps 50 --updates 3 \
  --repeats 2 --variants default,full --pieces default --json $out/throughput_h200.json"
job 1 goal "python benchmarks/time_to_solve_goal.py --preset gpu --set randomize.families=all \
  --max-seconds 40 --eval-every 1 --json $out/time_to_solve_goal_h200.json && \
  python -m jaxnav.train --env goal --preset gpu --randomize.families all --out /tmp/goal-gpu \
  --no-progress && python benchmarks/moving_obstacles.py --checkpoint /tmp/goal-gpu --episodes 20 \
  --steps 500 --json $out/moving_obstacles_goal_h200.json"
job 2 movers "python -m jaxnav.train --preset gpu --randomize.moving-count 0 3 \
  --out /tmp/avoid-movers --no-progress && python benchmarks/moving_obstacles.py --checkpoint \
  /tmp/avoid-movers --episodes 20 --json $out/moving_obstacles_avoid_movers_h200.json && \
  python benchmarks/env_rollout.py --num-envs 65536 --steps 64 --repeats 2 \
  --variants default,movers --json $out/env_rollout_h200_movers.json"
job 3 vs_brax "python benchmarks/vs_brax.py --preset gpu --num-envs 8192 --steps 52428800 \
  --eval-every 20 --trainers jaxnav,jaxnav-reset-all,brax --json $out/vs_brax_h200.json"
wait
for f in $out/*.log; do echo "== $f"; tail -n 12 $f; done
