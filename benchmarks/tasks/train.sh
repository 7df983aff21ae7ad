#!/usr/bin/env bash
# Train the task's ACT with LeRobot's own lerobot-train, seeded (the exact command of the
# committed checkpoints; ~13 min for push, ~9 min for reach-moving on a 2-core CPU machine).
#   bash benchmarks/tasks/train.sh push out/tasks/data/push out/tasks/train/push [steps]
set -euo pipefail
task=$1 data=$2 out=$3 steps=${4:-3000}
rm -rf "$out"
exec "${PYTHON_BIN:-.venv/bin}/lerobot-train" \
  --dataset.repo_id="local/metaworld_${task}" --dataset.root="$data" \
  --policy.type=act --policy.device=cpu --policy.push_to_hub=false \
  --policy.dim_model=128 --policy.n_heads=4 --policy.n_encoder_layers=2 --policy.n_decoder_layers=1 \
  --policy.dim_feedforward=512 --policy.use_vae=false --policy.optimizer_lr=3e-4 \
  --policy.chunk_size=20 --policy.n_action_steps=10 \
  --batch_size=64 --steps="$steps" --seed=1 --num_workers=0 \
  --log_freq=250 --save_freq="$steps" --env_eval_freq=0 --wandb.enable=false \
  --output_dir="$out"
