#!/usr/bin/env bash
# The loop, measured (issue 21): a policy trained on the tool's data, evaluated on 50 new seeds.
#
#   bench/train_eval.sh TASK [--demos N] [--steps N] [--sources K] [--humanlike] [--images] [--action MODE] [--lr LR]
#                       [--schedule constant|cosine] [--ensemble C] [--dropout P] [--keep-idle] [--episodes N]
#                       [--max-seconds T] [--work DIR]
#
#   1. K source demos (seeds 0..K-1) from the task's solving script (--humanlike: the same script with a
#      person's pauses, overshoots and corrections, bench/humanlike.py);
#   2. `teleop generate` N demos from them (2 local workers; default 200, pick_place and stack 2,000), on seeds from 100, or
#      from 2000 past 500 demos: the seeds tried never reach the evaluation's;
#   3. `teleop export` (2 workers): robot state, the objects' poses (observation.environment_state) and the task's
#      action mode (joint targets; ee_pose for pick_place and stack, see below; --action overrides); no images
#      (--images: front and wrist cameras at 96x96 as PNG frames); idle frames left out (`--drop-idle`: a person's
#      pauses, the waits for the gripper; --keep-idle keeps them);
#   4. `lerobot-train` ACT with the hyper-parameters below, on DEVICE (cpu; cuda where there is one): a constant
#      learning rate of 1e-4 (pick_place, stack: 3e-4 decayed to 1e-5 on a cosine, after 500 warm-up steps); the policy
#      averages its chunks' predictions for each tick with weights exp(-C i), i = 0 the oldest (ACT's temporal
#      ensembling; C = 0.01, pick_place and stack 0.1); 6,000 steps (pick_place and stack 18,000, handover 9,000); dropout P
#      in the transformer (default none, see below);
#   5. `teleop eval` on seeds 1000-1049 (--episodes N: 1000..1000+N-1; its JSON in WORK/eval.json), each episode
#      failed after T simulated seconds (--max-seconds, default 20 as in `teleop eval`).
# Prints one JSON object on stdout: task, demos, sources, humanlike, images, action, lr, schedule, ensemble, dropout, drop_idle, steps,
# train_seconds, success_rate, ci95, failure_breakdown. Progress and the tools' logs go to stderr. Steps already done in
# WORK with the same settings are not redone; a step whose settings changed is redone, with every step after it.
# Environment: DEMOS, STEPS, SOURCES, EPISODES change those defaults (the options win); E2E_DIR is where the default
# WORK is made (out/e2e); BATCH (64) and WORKERS (2) are lerobot-train's; DEVICE, PYTHON, TELEOP, LEROBOT_TRAIN.
# The whole script is one block, read before any of it runs: a run takes ~25 min, and bash reads a plain script as it
# goes, so an edit of this file meanwhile (a checkout updated, a setting changed) would run half of each version.
{
set -Eeuo pipefail
usage="usage: bench/train_eval.sh TASK [--demos N] [--steps N] [--sources K] [--humanlike] [--images] [--action MODE] [--lr LR] [--schedule constant|cosine] [--ensemble C] [--dropout P] [--keep-idle] [--episodes N] [--max-seconds T] [--work DIR]"
# Any failure ends with one line on stderr naming the step (after the failing tool's own words): a command that
# fails (the ERR trap; -E carries it into functions, and a subshell's failure is named once, by its parent),
# an option or setting refused (fail), or a stop by a signal (the EXIT trap, when nothing was said).
task="" step="setup" said=0
fail() { echo "train_eval.sh${task:+ [$task]}: $1" >&2; said=1; exit "${2:-2}"; }
trap 'rc=$?; if [ "$BASH_SUBSHELL" = 0 ]; then said=1
    echo "train_eval.sh [$task]: $step failed (exit $rc, line $LINENO: $BASH_COMMAND)" >&2; fi' ERR
trap 'rc=$?; [ $rc = 0 ] || [ $said = 1 ] || echo "train_eval.sh [$task]: stopped during $step (exit $rc)" >&2' EXIT
trap 'exit 130' INT; trap 'exit 143' TERM  # so that a Ctrl-C or a kill goes through the EXIT trap's line too
[ $# -gt 0 ] && [[ "$1" != -* ]] || fail "a TASK comes first ($usage)"
task=$1
shift
demos=${DEMOS:-}  # DEMOS, STEPS, SOURCES, EPISODES: the counts' defaults from the environment (the options win)
steps=${STEPS:-}
sources=${SOURCES:-3}
humanlike=0
images=0
drop_idle=1
action=""
lr=""
schedule=""
ensemble=""
dropout=0
episodes=${EPISODES:-50}
max_seconds=20
work=""
while [ $# -gt 0 ]; do
    case "$1" in
        --humanlike) humanlike=1; shift; continue ;;
        --images) images=1; shift; continue ;;
        --keep-idle) drop_idle=0; shift; continue ;;
        --demos|--steps|--sources|--action|--lr|--schedule|--ensemble|--dropout|--episodes|--max-seconds|--work)
            [ $# -ge 2 ] || fail "$1 takes a value ($usage)" ;;
        *) fail "unknown option $1 ($usage)" ;;
    esac
    case "$1" in
        --demos) demos=$2 ;;
        --steps) steps=$2 ;;
        --sources) sources=$2 ;;
        --action) action=$2 ;;
        --lr) lr=$2 ;;
        --schedule) schedule=$2 ;;
        --ensemble) ensemble=$2 ;;
        --dropout) dropout=$2 ;;
        --episodes) episodes=$2 ;;
        --max-seconds) max_seconds=$2 ;;
        --work) work=$2 ;;
    esac
    shift 2
done
case "$task" in
    lift) script=lift_pick.json ;;
    stack) script=stack_pick.json ;;
    pick_place) script=pick_place.json ;;
    *) script=$task.json ;;
esac
# Placing one cube on another wants centimetres over a 4-D space of both cubes' places: stack learns more
# from an absolute hand target (ee_pose, near a linear function of the cubes' poses), from more demos
# (measured at 12,000 steps: joint targets 0.16 at 20,000; ee_pose 0.22 from 200 demos, 0.40 from 1,000) and
# from a learning rate that falls to fine steps by the end (at a constant 1e-4, 20,000 steps did no better
# than 12,000: 0.32), and from older predictions counting more in the ensembling (one checkpoint on validation
# seeds 5000-5049, none of them generated or evaluated: 0.62 with C = 0.1 against 0.42 with 0.01).
# No dropout (ACT's preset has 0.1): 20,000 steps see each of stack's 2,000 demos' frames under 3 times, so the model
# underfits rather than overfits; with 0.1 it set the red cube down 1-4 cm off the blue one (loss 0.028 at the end,
# success 0.52), without it the loss reached 0.010 and the success 0.98, and a step costs a third less compute.
# pick_place learns the same way: lift's settings (joint targets, 200 demos, 1e-4, C = 0.01) gave 0.38 without
# dropout (23 passes over each frame; 15 timeouts, 13 still holding the cube at the end), stack's gave 0.98.
# pick_place and stack train 18,000 steps: 27.9-29.5 min on 2 cores in the machine's slow state (the data workers are then
# the bottleneck: ~10.6 steps/s, against 14-15 on its faster days). lift and the other joint-target tasks train 6,000:
# the whole run as the README prints it (sources, 200 generated, export, training, 50 evaluated) must stay within
# 30 min on 2 cores: measured alone on 2026-11-28 in the machine's slow state (0.236 s a step), 1,620 s in all,
# 1,413 s of training, 50 of 50 lifted (docs/learning.md, "What a run costs").
# handover (two arms) gets 9,000: its data workers feed 6-8 steps/s (62,325 frames of 14-D state and action from
# 200 episodes of ~310 frames), against lift's 10.6-15, so 18,000 steps would take 40-55 min; 9,000 took 20.6 min
# (2026-11-26) and the policy succeeded on 50 of 50 new seeds.
case "$task" in
    handover) steps=${steps:-9000} ;;
    stack|pick_place) steps=${steps:-18000} ;;
    *) steps=${steps:-6000} ;;
esac
case "$task" in  # the task's defaults, for what the options leave unset
    stack|pick_place) defaults=(ee_pose 2000 3e-4 cosine 0.1) ;;
    *) defaults=(joint 200 1e-4 constant 0.01) ;;
esac
action=${action:-${defaults[0]}} demos=${demos:-${defaults[1]}} lr=${lr:-${defaults[2]}}
schedule=${schedule:-${defaults[3]}} ensemble=${ensemble:-${defaults[4]}}
case "$action" in joint|ee_pose|ee_delta) ;; *) fail "--action must be joint, ee_pose or ee_delta" ;; esac
case "$schedule" in constant|cosine) ;; *) fail "--schedule must be constant or cosine" ;; esac
[[ "$lr" =~ ^[0-9.]+(e-?[0-9]+)?$ ]] || fail "--lr must be a number, such as 1e-4"
[[ "$dropout" =~ ^(0(\.[0-9]*)?|\.[0-9]+)$ ]] || fail "--dropout must be a number from 0 to below 1, such as 0.1"
[[ "$max_seconds" =~ ^([0-9]+(\.[0-9]*)?|\.[0-9]+)$ ]] && [[ ! "$max_seconds" =~ ^[0.]+$ ]] \
    || fail "--max-seconds must be simulated seconds above 0, such as 20"
[[ "$ensemble" =~ ^-?[0-9.]+(e-?[0-9]+)?$ ]] || fail "--ensemble must be a number, such as 0.01"
for n in "$demos" "$steps" "$sources" "$episodes"; do
    [[ "$n" =~ ^[1-9][0-9]*$ ]] || fail "--demos, --steps, --sources and --episodes (DEMOS, STEPS, SOURCES, EPISODES) take a whole number above 0, not '$n'"
done
# Generated seeds run upward from here (a few more than N are tried), clear of the evaluation's 1000 and up.
gen_seed=$(( demos > 500 ? (episodes > 1000 ? 1000 + episodes : 2000) : 100 ))
root=$(cd "$(dirname "$0")/.." && pwd)
[ -f "$root/scenes/scripts/$script" ] || fail "no solving script scenes/scripts/$script for task $task"
# The task file's first robot records, generates and evaluates (panda for the one-arm built-ins; bimanual for handover)
robot=$(cd "$root" && "${PYTHON:-$root/.venv/bin/python}" -c "import sys; from scenes.tasks.registry import find_task; \
r = find_task(sys.argv[1]).robots; print(r[0] if r else 'panda')" "$task" 2>/dev/null) \
    || fail "no task named $task"
# The default WORK names the settings that make its data (no `$([ x ] && echo y)` in an assignment: under set -e
# a false test there ends the script)
if [ -z "$work" ]; then
    work=${E2E_DIR:-$root/out/e2e}/$task-d$demos-s$sources
    if [ $humanlike = 1 ]; then work+=h; fi
    if [ $images = 1 ]; then work+=i; fi
    if [ $drop_idle = 0 ]; then work+=-keepidle; fi
fi
device=${DEVICE:-cpu}
python=${PYTHON:-$root/.venv/bin/python}
teleop=${TELEOP:-$root/.venv/bin/teleop}
train=${LEROBOT_TRAIN:-$root/.venv/bin/lerobot-train}
export HF_HUB_OFFLINE=1 MUJOCO_GL=${MUJOCO_GL:-egl} PYTHONPATH="$root${PYTHONPATH:+:$PYTHONPATH}"
mkdir -p "$work"
work=$(cd "$work" && pwd)  # absolute: lerobot-train is handed $work/ds from inside $work
cd "$work"
say() { echo "train_eval.sh [$task]: $*" >&2; }
# What each step's result depends on, kept beside it in WORK/settings/STEP: a rerun in the same WORK with other
# settings redoes the first step they touch and every step after it (a step from before these files is redone too).
keys=("task=$task sources=$sources humanlike=$humanlike")
keys+=("${keys[0]} demos=$demos seed=$gen_seed")
keys+=("${keys[1]} action=$action images=$images drop_idle=$drop_idle")
keys+=("${keys[2]} steps=$steps lr=$lr schedule=$schedule ensemble=$ensemble dropout=$dropout batch=${BATCH:-64} device=$device")
eval_key="${keys[3]} episodes=$episodes"
if [ "$max_seconds" != 20 ]; then eval_key+=" max_seconds=$max_seconds"; fi  # as before --max-seconds: 20 s redoes nothing
keys+=("$eval_key")
steps_done=(src gen ds train eval)  # each step's name, and what it leaves in WORK when it is done:
outputs=(src gen ds train_seconds eval.json)
stale=0
for i in "${!outputs[@]}"; do
    if [ $stale = 1 ] || { [ -e "${outputs[$i]}" ] && [ "$(cat "settings/${steps_done[$i]}" 2>/dev/null)" != "${keys[$i]}" ]; }; then
        [ -e "${outputs[$i]}" ] && say "redoing ${steps_done[$i]}: its settings changed"
        rm -rf "${outputs[$i]}" "settings/${steps_done[$i]}"
        stale=1
    fi
done
mkdir -p settings
done_step() { echo "${keys[$1]}" > "settings/${steps_done[$1]}"; }

if [ ! -d src ]; then
    step="recording the source demos"
    say "$sources source demos$([ $humanlike = 1 ] && echo ' (human-like)')"
    mkdir -p src.tmp
    for ((s = 0; s < sources; s++)); do
        src_script="$root/scenes/scripts/$script"
        if [ $humanlike = 1 ]; then
            "$python" "$root/bench/humanlike.py" "$src_script" --seed "$s" > "src.tmp/script_$s.json"
            src_script="$work/src.tmp/script_$s.json"
        fi
        "$teleop" run --scene "$task" --robot "$robot" --device "script:$src_script" --seed "$s" --record src.tmp >&2
    done
    mv src.tmp src
    done_step 0
fi
if [ ! -d gen ]; then
    step="generation"
    say "generating $demos demos"
    "$teleop" generate src --out gen.tmp --num "$demos" --seed "$gen_seed" --workers 2 >&2
    mv gen.tmp gen
    done_step 1
fi
if [ ! -d ds ]; then
    step="export"
    say "exporting"
    idle=(); [ $drop_idle = 1 ] && idle=(--drop-idle)
    # PNG frames, not video: lerobot-train then reads a sample in milliseconds instead of seeking in an MP4
    view=(--cameras none); [ $images = 1 ] && view=(--cameras front,wrist --image-size 96x96 --no-video)
    "$teleop" export gen --out ds --repo-id "local/$task" --action "$action" "${view[@]}" --workers 2 "${idle[@]}" >&2
    done_step 2
fi
if [ ! -f train_seconds ]; then
    step="training"
    say "training ACT for $steps steps on $device"
    optimizer=(--policy.optimizer_lr="$lr")  # ACT's own preset: AdamW, weight decay 1e-4, a constant rate
    if [ "$schedule" = cosine ]; then
        optimizer=(--use_policy_training_preset=false --optimizer.type=adamw --optimizer.lr="$lr" --optimizer.weight_decay=1e-4
                   --optimizer.grad_clip_norm=10 --scheduler.type=cosine_decay_with_warmup --scheduler.num_warmup_steps=500
                   --scheduler.num_decay_steps="$steps" --scheduler.peak_lr="$lr" --scheduler.decay_lr=1e-5)
    fi
    # ACT normalizes the types its preset names (images, robot state, action) and passes any other
    # through as it is: without ENV here the objects' poses reach the network raw, in metres (a spread
    # of a few centimetres, against unit spreads for the joints).
    normalization='{"VISUAL": "MEAN_STD", "STATE": "MEAN_STD", "ENV": "MEAN_STD", "ACTION": "MEAN_STD"}'
    rm -rf train
    t0=$(date +%s)
    # ACT on the robot state and the objects' poses, sized for 2 CPU cores: one encoder layer of width 128
    # (4 heads), no VAE (the scripted and generated demos are one mode per scene), chunks of 20 actions
    # (0.67 s at 30 Hz) predicted at every tick and averaged (ACT's temporal ensembling, coefficient C:
    # pick_place 0.80 against 0.62 running 10 of each chunk, same checkpoint); two data-loading workers.
    # One torch thread: a model this small gains nothing from intra-op threads, and two of them fight the
    # data workers for the 2 cores (measured: 14-15 steps/s alone, under 1-2 steps/s oversubscribed).
    OMP_NUM_THREADS=${OMP_NUM_THREADS:-1} MKL_NUM_THREADS=${MKL_NUM_THREADS:-1} \
    "$train" --dataset.repo_id="local/$task" --dataset.root="$work/ds" --policy.type=act --policy.device="$device" \
        --policy.push_to_hub=false --policy.pretrained_backbone_weights=null \
        --policy.dim_model=128 --policy.n_heads=4 --policy.dim_feedforward=512 --policy.n_encoder_layers=1 \
        --policy.use_vae=false --policy.chunk_size=20 --policy.n_action_steps=1 --policy.dropout="$dropout" \
        --policy.temporal_ensemble_coeff="$ensemble" "${optimizer[@]}" \
        --policy.normalization_mapping="$normalization" \
        --batch_size="${BATCH:-64}" --steps="$steps" --num_workers="${WORKERS:-2}" --wandb.enable=false --save_freq="$steps" \
        --log_freq=500 --output_dir="$work/train" 2>&1 | tr '\r' '\n' | sed -u -E 's/^Training:.*\](INFO )/\1/' \
        | grep --line-buffered -v "^Training:" >&2 || true
    [ -d "$work/train/checkpoints/last/pretrained_model" ] || fail "training failed: lerobot-train made no checkpoint" 1
    echo $(( $(date +%s) - t0 )) > train_seconds
    done_step 3
fi
if [ ! -f eval.json ]; then
    step="evaluation"
    say "evaluating on seeds 1000-$((999 + episodes))"
    # One torch thread here too: two evaluations side by side (bench/learning_curve.py --jobs 2) each took
    # over 5 min with the default threads, against 50 s with one
    OMP_NUM_THREADS=${OMP_NUM_THREADS:-1} MKL_NUM_THREADS=${MKL_NUM_THREADS:-1} \
    "$teleop" eval --policy train/checkpoints/last/pretrained_model --scene "$task" --robot "$robot" --episodes "$episodes" --seed 1000 \
        --max-seconds "$max_seconds" --device "$device" --json > eval.json.tmp
    mv eval.json.tmp eval.json
    done_step 4
fi
step="the report"
"$python" - "$task" "$demos" "$sources" "$humanlike" "$images" "$action" "$lr" "$schedule" "$ensemble" "$dropout" "$drop_idle" "$steps" "$(cat train_seconds)" <<'EOF'
import json, sys
task, demos, sources, humanlike, images, action, lr, schedule, ensemble, dropout, drop_idle, steps, seconds = sys.argv[1:]
report = json.load(open("eval.json"))
print(json.dumps({
    "task": task, "demos": int(demos), "sources": int(sources), "humanlike": humanlike == "1", "images": images == "1",
    "action": action, "lr": float(lr), "schedule": schedule, "ensemble": float(ensemble), "dropout": float(dropout), "drop_idle": drop_idle == "1", "steps": int(steps), "train_seconds": int(seconds), "success_rate": report["success_rate"], "ci95": report["ci95"],
    "failure_breakdown": report.get("failure_breakdown", {}),
}))
EOF
exit
}
