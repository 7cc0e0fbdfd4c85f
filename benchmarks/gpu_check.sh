#!/usr/bin/env bash
# The GPU recipe measured in one go on a CUDA machine (experiment=gpu; see conf/experiment/gpu.yaml).
#   bash benchmarks/gpu_check.sh            # from the repository root, on a machine with a GPU
# 1. ms per update and env steps per second at the GPU recipe: eager, compiled, and compiled with
#    the update captured in a CUDA graph, side by side (benchmarks/train_speed.py);
# 2. 1M frames of `icco train experiment=gpu` end to end for ICCO, then ICCO and QMIX (FULL) as two
#    runs at once on the one GPU (the sweep's launcher runs jobs in parallel the same way);
# 3. one whole ICCO run at the recipe's 5M frames, its greedy evaluations included.
# Writes benchmarks/results/train_speed_h200.json and benchmarks/results/gpu_train_h200.json
# (rendered in benchmarks/README.md). Python packages the machine lacks can travel as wheels in
# .whl/ (installed with --no-index); PYTHON picks the interpreter (default python3). SPEED=0 skips
# step 1 (its JSON from an earlier run stays).
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
"$PY" -c "import sys, torch; sys.exit(0 if torch.cuda.is_available() else 'gpu_check.sh: no CUDA device here')"
OUT=${RUNS:-runs/gpu_check}
mkdir -p benchmarks/results "$OUT"
if [ -d .whl ]; then
  "$PY" -m pip install -q --no-index --find-links .whl -e . >"$OUT/pip.log" 2>&1 \
    || { cat "$OUT/pip.log"; exit 1; }
fi
export TORCHINDUCTOR_CACHE_DIR=${TORCHINDUCTOR_CACHE_DIR:-$(cd "$OUT" && pwd)/inductor}
export WANDB_MODE=disabled LITELLM_LOCAL_MODEL_COST_MAP=True
nvidia-smi --query-gpu=name,memory.total --format=csv,noheader || true

[ "${SPEED:-1}" = 0 ] || "$PY" benchmarks/train_speed.py --device cuda --experiment gpu --paths eager compiled graphs \
  --threads 8 --batches 8 --run-dir "$OUT/speed" --out train_speed_h200.json

train() {  # method folder frames
  "$PY" -m icco_torchrl train experiment=gpu "method=$1" train.total_frames="$3" \
    train.eval_interval=0 logger.progress=false "hydra.run.dir=$2" >"$2.log" 2>&1
}
rm -rf "$OUT/icco_alone" "$OUT/icco_pair" "$OUT/qmix_full_pair" "$OUT/icco_5m"
now() { date +%s.%N; }
since() { "$PY" -c "import sys; print(float(sys.argv[2]) - float(sys.argv[1]))" "$1" "$(now)"; }
start=$(now); train icco "$OUT/icco_alone" 1000000; alone=$(since "$start")
start=$(now)
train icco "$OUT/icco_pair" 1000000 & a=$!
train qmix_full "$OUT/qmix_full_pair" 1000000 & b=$!
wait $a $b; pair=$(since "$start")
start=$(now)
"$PY" -m icco_torchrl train experiment=gpu method=icco logger.progress=false \
  "hydra.run.dir=$OUT/icco_5m" >"$OUT/icco_5m.log" 2>&1
whole=$(since "$start")

"$PY" - "$OUT" "$alone" "$pair" "$whole" <<'PYEOF'
import csv, json, sys
from pathlib import Path
import torch
out, alone, pair, whole = Path(sys.argv[1]), *map(float, sys.argv[2:5])
def last(run, name):  # a run's last row of one of its CSVs
    return list(csv.DictReader((out / run / name).open()))[-1]
def sps(run):  # the run's own env steps per second (its last timing row)
    row = last(run, "timing.csv")
    return dict(env_steps_per_s=float(row["sps"]), frames=int(row["frames"]))
runs = {name: sps(name) for name in ("icco_alone", "icco_pair", "qmix_full_pair")}
row, final = last("icco_5m", "timing.csv"), last("icco_5m", "eval.csv")
train = [float(r["time_train"]) for r in csv.DictReader((out / "icco_5m" / "timing.csv").open())]
run_5m = dict(**sps("icco_5m"), wall_s=whole, **{
    k: float(row[f"time_{k}"]) for k in ("collect", "train", "eval")},
    slowest_batch_train_s=max(b - a for a, b in zip(train, train[1:])),  # the first: its compile
    final_eval_reward=float(final["reward"]), final_eval_reward_std=float(final["reward_std"]))
result = {"gpu": torch.cuda.get_device_name(0), "torch": torch.__version__,
          "recipe": "experiment=gpu (1024 envs x 16 steps, 8 updates of 1024 x 16, replay ratio 8)",
          "wall_s": {"icco_alone": alone, "two_runs_at_once": pair}, "runs": runs,
          "icco_5m": run_5m}
Path("benchmarks/results/gpu_train_h200.json").write_text(json.dumps(result, indent=1) + "\n")
print(json.dumps(result, indent=1))
PYEOF
