#!/usr/bin/env bash
# Train ACT (camera `top` 160x120 + joint state, no environment_state) on the recorded demos, on the CPU.
# Usage: scripts/lerobot_aloha/train_act.sh [DATASET_ROOT] [OUTPUT_DIR] [STEPS]
set -euo pipefail
ROOT=${1:-/tmp/aloha_act/demos}
OUT=${2:-/tmp/aloha_act/train_act}
STEPS=${3:-3000}
export HF_HUB_OFFLINE=1 HF_DATASETS_OFFLINE=1 OMP_NUM_THREADS=1 MKL_NUM_THREADS=1
# The Python 3.12 environment with the lerobot extra (see README.md); LEROBOT_TRAIN overrides it.
REPO="$(cd "$(dirname "$0")/../.." && pwd)"
exec "${LEROBOT_TRAIN:-$REPO/.venv-py312/bin/lerobot-train}" \
  --dataset.repo_id=local/aloha_transfer_cube --dataset.root="$ROOT" \
  --policy.type=act --policy.device=cpu --policy.push_to_hub=false \
  --policy.pretrained_backbone_weights=null \
  '--policy.input_features={"observation.images.top": {"type": "VISUAL", "shape": [3, 120, 160]}, "observation.state": {"type": "STATE", "shape": [14]}}' \
  --policy.dim_model=256 --policy.dim_feedforward=1024 \
  --policy.chunk_size=100 --policy.n_action_steps=100 \
  --policy.optimizer_lr=1e-4 --policy.optimizer_lr_backbone=1e-4 \
  --output_dir="$OUT" --steps="$STEPS" --batch_size=8 --save_freq=500 --log_freq=50 \
  --num_workers=1 --wandb.enable=false
