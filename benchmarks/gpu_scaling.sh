#!/usr/bin/env bash
# On a 4-GPU host: the gpu preset's time to the suite's bar on one GPU, then PPO scaling over 1, 2, 4.
export PYTHONUNBUFFERED=1
out=${OUT:?set OUT}
CUDA_VISIBLE_DEVICES=0 timeout 200 python benchmarks/time_to_solve.py --preset gpu --full \
  --max-seconds 60 --eval-every 5 --json $out/time_to_solve_h200_gpu.json > $out/tts.log 2>&1
tail -n 3 $out/tts.log
timeout 330 python benchmarks/scaling.py --devices 1,2,4 --num-envs 65536 --updates 3 --repeats 2 \
  --timeout 150 --json $out/scaling_h200.json 2>&1 | tail -n 20
