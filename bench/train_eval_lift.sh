#!/usr/bin/env bash
# The end-to-end figure of issue 13: a policy trained on generated lift demos, evaluated on 50 new seeds.
#   bench/train_eval_lift.sh WORKDIR [STEPS] [DEMOS]
# 3 scripted source demos (seeds 0-2) -> `teleop generate` DEMOS lift demos (seeds from 100) ->
# `teleop export` (front + wrist at 96x96 PNG frames, joint actions) -> `lerobot-train` ACT (width DIM,
# default 256; chunks of 30 actions, 1 s) for STEPS steps on
# this machine's CPU or GPU -> `teleop eval` on seeds 1000-1049. Prints the eval's JSON last; the
# training time is in WORKDIR/train_seconds.
set -Eeuo pipefail
# A failing step ends the script with one line on stderr naming it (after the tool's own words)
trap 'rc=$?; [ "$BASH_SUBSHELL" != 0 ] || echo "train_eval_lift.sh: failed (exit $rc, line $LINENO: $BASH_COMMAND)" >&2' ERR
[ $# -ge 1 ] || { echo "train_eval_lift.sh: usage: bench/train_eval_lift.sh WORKDIR [STEPS] [DEMOS]" >&2; exit 2; }
work=$1
steps=${2:-2000}
demos=${3:-200}
device=${DEVICE:-cpu}
root=$(cd "$(dirname "$0")/.." && pwd)
teleop=${TELEOP:-$root/.venv/bin/teleop}
train=${LEROBOT_TRAIN:-$root/.venv/bin/lerobot-train}
export HF_HUB_OFFLINE=1 MUJOCO_GL=${MUJOCO_GL:-egl}
mkdir -p "$work"
cd "$work"
[ -d src ] || "$teleop" run --device "script:$root/scenes/scripts/lift_pick.json" --episodes 3 --seed 0 --record src >&2
[ -d gen ] || "$teleop" generate src --out gen --num "$demos" --seed 100 >&2
# PNG frames, not video: lerobot-train then reads a sample in milliseconds instead of seeking in an MP4
[ -d ds ] || "$teleop" export gen --out ds --repo-id local/lift_gen --cameras front,wrist --image-size 96x96 --no-video >&2
if [ ! -d train ]; then
    t0=$(date +%s)
    "$train" --dataset.repo_id=local/lift_gen --dataset.root="$work/ds" --policy.type=act --policy.device="$device" \
        --policy.push_to_hub=false --policy.pretrained_backbone_weights=null --steps="$steps" --batch_size="${BATCH:-8}" \
        --policy.dim_model="${DIM:-256}" --policy.dim_feedforward="$(( ${DIM:-256} * 4 ))" --policy.chunk_size=30 --policy.n_action_steps=30 \
        --num_workers=0 --wandb.enable=false --save_freq="${SAVE_FREQ:-$steps}" --log_freq=50 --output_dir="$work/train" >&2
    echo $(( $(date +%s) - t0 )) > train_seconds
fi
"$teleop" eval --policy train/checkpoints/last/pretrained_model --scene lift --episodes 50 --seed 1000 \
    --device "$device" --record rollouts --json
