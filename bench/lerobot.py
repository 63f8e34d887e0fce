"""LeRobot's own commands on the simulation (issue 58): `teleop bench --only lerobot --json`.

  lerobot_record_hz          the loop rate `lerobot-record` holds on `--robot.type=mujoco_teleop` (so101, two 96x96
                             cameras, an emulated SO-101 leader on a pseudo-terminal): steps over the wall-clock span
                             of each episode (the wall time of each step in this tool's own episode, recorded alongside
                             with --robot.record_dir), the median over the episodes (goal >= 30, its fps; the loop
                             sleeps to it, so about 30 is the most it shows)
  lerobot_loop_ceiling_hz    the rate LeRobot's loop timing itself reaches with no work at all (its precise_sleep is
                             time.sleep on Linux, which wakes a little late): the most lerobot_record_hz can show here
  lerobot_record_frames_s    frames of the dataset's episodes over episode_time_s (one frame short when the loop
                             runs a hair under fps: LeRobot stops at the first tick past the episode's time)
  lerobot_eval_steps_s       environment steps a second in `lerobot-eval --env.type=mujoco_teleop` (state only, one
                             env, a small ACT checkpoint, LeRobot's default 50 episodes of 150 steps): steps over its
                             `eval_s`, which includes the rgb_array frame it renders each step of its first 10 episodes
                             and the writing of their videos; the median of 3 runs
  teleop_eval_steps_s        `teleop eval`'s steps_per_s for the same checkpoint on the same seeds (each run right after
                             a lerobot-eval run; the median of 3)
  lerobot_eval_vs_teleop_eval  the first over the second (goal: within 10 % of 1)
  lerobot_env_steps_s        the env alone through LeRobot's vector env (no policy), in this process: what the
                             simulation costs of lerobot-eval's step
  lerobot_env_render_steps_s the same with an rgb_array render a step, as lerobot-eval renders its videos
                             (10 episodes by default; software GL where there is no GPU)
  teleop_env_steps_s         the TeleopEnv that `teleop eval` steps, alone, on the same seeds
  lerobot_env_vs_teleop_env  lerobot_env_steps_s over teleop_env_steps_s: what the plugin's env and LeRobot's vector
                             env add to a step (the rest of lerobot-eval's time per step is its own loop: the policy's
                             processors, a success tally over the whole rollout and a progress bar each step)

Each LeRobot command runs in its own process, as a user runs it (the plugin found by its distribution name).
"""

from __future__ import annotations

import json
import math
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

from tests.servo_emulator import FeetechEmulator, from_lerobot

ROOT = Path(__file__).resolve().parent.parent
BIN = Path(sys.executable).parent
PICK = ROOT / "scenes" / "scripts" / "lift_pick.json"
FPS = 30
EVAL_EPISODES = 50  # lerobot-eval's default --eval.n_episodes (it renders the first 10 for its videos)


def _env() -> dict[str, str]:
    return {**os.environ, "HF_HUB_OFFLINE": "1", "WANDB_MODE": "disabled", "CUDA_VISIBLE_DEVICES": "",
            "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl"), "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


def _run(argv: list[str], cwd: Path, timeout: float = 1800) -> subprocess.CompletedProcess:
    result = subprocess.run(argv, cwd=cwd, env=_env(), capture_output=True, text=True, timeout=timeout)
    if result.returncode != 0:
        raise RuntimeError(f"{Path(argv[0]).name} exited {result.returncode}: {result.stderr[-2000:]}")
    return result


def _motion(leader: FeetechEmulator, seconds: float = 4.0, step: float = 0.02) -> dict:
    """A looping 0.25 Hz sine on shoulder_pan and elbow_flex (LeRobot's degrees on the wire)."""
    ts = [round(i * step, 6) for i in range(int(round(seconds / step)) + 1)]
    positions = {}
    for motor, cal in leader.calibration.items():
        if motor == "gripper":
            positions[str(cal.id)] = [from_lerobot(50.0, cal, "range_0_100") for _ in ts]
        else:
            amp = 20.0 if motor in ("shoulder_pan", "elbow_flex") else 0.0
            positions[str(cal.id)] = [from_lerobot(amp * math.sin(2 * math.pi * t / seconds), cal, "degrees") for t in ts]
    return {"t": ts, "positions": positions, "loop": True}


def record_hz(work: Path, episodes: int, seconds: float) -> tuple[float, float]:
    """(the loop rate lerobot-record held: steps over the wall-clock span of this tool's own episodes recorded
    alongside (--robot.record_dir; each step's wall time), the median over the episodes; frames a second of the
    dataset's episodes). LeRobot's loop ends an episode at the first tick past episode_time_s, so a loop a little
    slower than fps (time.sleep overshoots on Linux) loses the last frame: the second figure shows that."""
    import numpy as np
    from lerobot.datasets import LeRobotDataset

    from replay.episode import find_episodes, load_episode

    with FeetechEmulator.start(work, role="leader") as leader:
        leader.write_calibration_file(work / "cal", "arm")
        leader.play(_motion(leader))
        _run([str(BIN / "lerobot-record"), "--robot.type=mujoco_teleop", "--robot.robot=so101", "--robot.cameras=front,wrist",
              "--robot.image_size=96x96", f"--robot.fps={FPS}", f"--robot.record_dir={work / 'own'}", "--teleop.type=so101_leader",
              f"--teleop.port={leader.port}", "--teleop.id=arm", f"--teleop.calibration_dir={work / 'cal'}",
              "--teleop.num_read_retries=10",  # the emulator's process, not a servo: late on a loaded machine
              "--dataset.repo_id=bench/sim", f"--dataset.root={work / 'ds'}", f"--dataset.num_episodes={episodes}",
              f"--dataset.episode_time_s={seconds}", "--dataset.reset_time_s=0", f"--dataset.fps={FPS}",
              "--dataset.push_to_hub=false", "--dataset.single_task=Pick up the red cube and lift it.", "--display_data=false",
              "--play_sounds=false"], work)
    rates = []
    for path in find_episodes(work / "own"):
        wall = load_episode(path).wall_time
        if len(wall) > 1:
            rates.append((len(wall) - 1) / float(wall[-1] - wall[0]))
    if not rates:
        raise RuntimeError(f"lerobot-record left none of this tool's episodes in {work / 'own'}")
    frames = np.asarray(LeRobotDataset("bench/sim", root=work / "ds").hf_dataset.with_format("numpy")["episode_index"])
    return statistics.median(rates), statistics.median(float(np.sum(frames == e)) / seconds for e in range(episodes))


def loop_ceiling_hz(seconds: float, fps: float = FPS) -> float:
    """The rate LeRobot's record loop reaches doing nothing: its own timing (a tick's work measured, then
    `precise_sleep` for the rest of 1/fps, which is time.sleep on Linux and wakes a little late) with no robot,
    teleoperator or dataset, as long as one recorded episode. What `lerobot_record_hz` can reach on this machine."""
    import time

    from lerobot.utils.robot_utils import precise_sleep

    starts: list[float] = []
    t0 = time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        start = time.perf_counter()
        starts.append(start)
        precise_sleep(max(1.0 / fps - (time.perf_counter() - start), 0.0))
    return (len(starts) - 1) / (starts[-1] - starts[0])


def eval_rates(work: Path, episodes: int, steps: int, rounds: int) -> tuple[float, float]:
    """(lerobot-eval's steps a second, teleop eval's) for one small checkpoint on the same seeds: medians over
    `rounds` of the two run one after the other (a busy machine slows both alike)."""
    teleop = str(BIN / "teleop")
    _run([teleop, "run", "--device", f"script:{PICK}", "--record", str(work / "eps"), "--episodes", "2", "--json"], work)
    _run([teleop, "export", str(work / "eps"), "--out", str(work / "ds"), "--repo-id", "bench/lift", "--cameras", "none"], work)
    _run([str(BIN / "lerobot-train"), "--dataset.repo_id=bench/lift", f"--dataset.root={work / 'ds'}", "--policy.type=act",
          "--policy.device=cpu", "--policy.push_to_hub=false", "--policy.pretrained_backbone_weights=null", "--steps=1",
          "--batch_size=2", "--num_workers=0", "--wandb.enable=false", f"--output_dir={work / 'out'}"], work)
    model = work / "out" / "checkpoints" / "last" / "pretrained_model"
    theirs, ours = [], []
    for r in range(rounds):
        out = work / f"lerobot_eval_{r}"
        _run([str(BIN / "lerobot-eval"), f"--policy.path={model}", "--policy.device=cpu", "--env.type=mujoco_teleop",
              f"--env.fps={FPS}", f"--env.episode_length={steps}", f"--eval.n_episodes={episodes}", "--eval.batch_size=1",
              "--seed=1000", f"--output_dir={out}"], work)
        info = json.loads((out / "eval_info.json").read_text())["overall"]
        theirs.append(info["n_episodes"] * steps / info["eval_s"])
        ours.append(json.loads(_run([teleop, "eval", "--policy", str(model), "--episodes", str(episodes), "--seed", "1000",
                                     "--max-seconds", str(steps / FPS), "--json"], work).stdout)["steps_per_s"])
    return statistics.median(theirs), statistics.median(ours)


def env_rates(steps: int) -> tuple[float, float, float]:
    """Steps a second (medians of 3 seeds, the three kinds taken in turn on each): the env through LeRobot's vector
    env as lerobot-eval makes it (its wrappers: FreezeAfterEpisodeEnd, TimeLimit, LeRobot's keys), the same with a
    render a step, and the `TeleopEnv` that `teleop eval` steps, alone (no vector env)."""
    import time

    import numpy as np
    import teleop.lerobot_plugin  # noqa: F401
    from lerobot.envs.configs import EnvConfig
    from lerobot.envs.utils import NEW_ROLLOUT_OPTION

    from teleop.learn.gym_env import TeleopEnv

    vec = EnvConfig.get_choice_class("mujoco_teleop")(episode_length=steps).create_envs(1)["mujoco_teleop"][0]
    plain = TeleopEnv("lift", "panda", cameras=(), max_seconds=steps / FPS)
    action = np.zeros((1, *vec.single_action_space.shape), np.float32)
    rates: dict[str, list[float]] = {"vec": [], "render": [], "plain": []}
    try:
        for seed in range(3):
            for kind in rates:
                if kind == "plain":
                    plain.reset(seed=1000 + seed)
                    step = lambda: plain.step(action[0])  # noqa: E731
                else:
                    vec.reset(seed=[1000 + seed], options={NEW_ROLLOUT_OPTION: True})
                    step = (lambda: (vec.step(action), vec.envs[0].render())) if kind == "render" else (lambda: vec.step(action))
                start = time.perf_counter()
                for _ in range(steps - 1):
                    step()
                rates[kind].append((steps - 1) / (time.perf_counter() - start))
    finally:
        vec.close()
        plain.close()
    return statistics.median(rates["vec"]), statistics.median(rates["render"]), statistics.median(rates["plain"])


def measure(quick: bool = False) -> dict[str, float]:
    with tempfile.TemporaryDirectory(prefix="bench_lerobot_") as tmp:
        work = Path(tmp)
        (work / "record").mkdir()
        (work / "eval").mkdir()
        hz, frames_s = record_hz(work / "record", episodes=2 if quick else 3, seconds=3.0 if quick else 5.0)
        ceiling = loop_ceiling_hz(3.0 if quick else 5.0)
        lerobot_rate, teleop_rate = eval_rates(work / "eval", episodes=4 if quick else EVAL_EPISODES, steps=60 if quick else 150,
                                               rounds=1 if quick else 3)
    env_rate, render_rate, plain_rate = env_rates(60 if quick else 150)
    return {"lerobot_record_hz": round(hz, 2), "lerobot_record_frames_s": round(frames_s, 2),
            "lerobot_loop_ceiling_hz": round(ceiling, 2), "lerobot_eval_steps_s": round(lerobot_rate, 1),
            "teleop_eval_steps_s": round(teleop_rate, 1), "lerobot_eval_vs_teleop_eval": round(lerobot_rate / teleop_rate, 3),
            "lerobot_env_steps_s": round(env_rate, 1), "lerobot_env_render_steps_s": round(render_rate, 1),
            "teleop_env_steps_s": round(plain_rate, 1), "lerobot_env_vs_teleop_env": round(env_rate / plain_rate, 3)}
