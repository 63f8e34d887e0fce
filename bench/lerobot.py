"""LeRobot's own commands on the simulation (issue 58): `teleop bench --only lerobot --json`.

  lerobot_record_hz          the loop rate `lerobot-record` holds on `--robot.type=mujoco_teleop` (so101, two 96x96
                             cameras, an emulated SO-101 leader on a pseudo-terminal): frames recorded per second of
                             each episode, the median over the episodes (goal >= 30, its fps; the loop sleeps to it,
                             so 30 is the most it shows)
  lerobot_eval_steps_s       environment steps a second in `lerobot-eval --env.type=mujoco_teleop` (state only, one
                             env, a small ACT checkpoint): steps over its `eval_s` (which includes its video rendering)
  teleop_eval_steps_s        `teleop eval`'s steps_per_s for the same checkpoint on the same seeds
  lerobot_eval_vs_teleop_eval  the first over the second (goal: within 10 % of 1)
  lerobot_env_steps_s        the env alone through LeRobot's vector env (no policy), in this process: what the
                             simulation costs of lerobot-eval's step
  lerobot_env_render_steps_s the same with an rgb_array render a step, as lerobot-eval renders its videos
                             (10 episodes by default; software GL where there is no GPU)

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


def record_hz(work: Path, episodes: int, seconds: float) -> float:
    import numpy as np
    from lerobot.datasets import LeRobotDataset

    with FeetechEmulator.start(work, role="leader") as leader:
        leader.write_calibration_file(work / "cal", "arm")
        leader.play(_motion(leader))
        _run([str(BIN / "lerobot-record"), "--robot.type=mujoco_teleop", "--robot.robot=so101", "--robot.cameras=front,wrist",
              "--robot.image_size=96x96", f"--robot.fps={FPS}", "--teleop.type=so101_leader", f"--teleop.port={leader.port}",
              "--teleop.id=arm", f"--teleop.calibration_dir={work / 'cal'}", "--dataset.repo_id=bench/sim",
              f"--dataset.root={work / 'ds'}", f"--dataset.num_episodes={episodes}", f"--dataset.episode_time_s={seconds}",
              "--dataset.reset_time_s=0", f"--dataset.fps={FPS}", "--dataset.push_to_hub=false",
              "--dataset.single_task=Pick up the red cube and lift it.", "--display_data=false", "--play_sounds=false"], work)
    frames = np.asarray(LeRobotDataset("bench/sim", root=work / "ds").hf_dataset.with_format("numpy")["episode_index"])
    return statistics.median(float(np.sum(frames == e)) / seconds for e in range(episodes))


def eval_rates(work: Path, episodes: int, steps: int) -> tuple[float, float]:
    """(lerobot-eval's steps a second, teleop eval's) for one small checkpoint on the same seeds."""
    teleop = str(BIN / "teleop")
    _run([teleop, "run", "--device", f"script:{PICK}", "--record", str(work / "eps"), "--episodes", "2", "--json"], work)
    _run([teleop, "export", str(work / "eps"), "--out", str(work / "ds"), "--repo-id", "bench/lift", "--cameras", "none"], work)
    _run([str(BIN / "lerobot-train"), "--dataset.repo_id=bench/lift", f"--dataset.root={work / 'ds'}", "--policy.type=act",
          "--policy.device=cpu", "--policy.push_to_hub=false", "--policy.pretrained_backbone_weights=null", "--steps=1",
          "--batch_size=2", "--num_workers=0", "--wandb.enable=false", f"--output_dir={work / 'out'}"], work)
    model = work / "out" / "checkpoints" / "last" / "pretrained_model"
    _run([str(BIN / "lerobot-eval"), f"--policy.path={model}", "--policy.device=cpu", "--env.type=mujoco_teleop",
          f"--env.fps={FPS}", f"--env.episode_length={steps}", f"--eval.n_episodes={episodes}", "--eval.batch_size=1",
          "--seed=1000", f"--output_dir={work / 'lerobot_eval'}"], work)
    info = json.loads((work / "lerobot_eval" / "eval_info.json").read_text())["overall"]
    ours = json.loads(_run([teleop, "eval", "--policy", str(model), "--episodes", str(episodes), "--seed", "1000",
                            "--max-seconds", str(steps / FPS), "--json"], work).stdout)
    return info["n_episodes"] * steps / info["eval_s"], ours["steps_per_s"]


def env_rates(steps: int) -> tuple[float, float]:
    """(steps a second of the env through LeRobot's SyncVectorEnv, the same rendering each step): medians of 3."""
    import time

    import numpy as np
    import teleop.lerobot_plugin  # noqa: F401
    from lerobot.envs.configs import EnvConfig

    vec = EnvConfig.get_choice_class("mujoco_teleop")(episode_length=steps).create_envs(1)["mujoco_teleop"][0]
    action = np.zeros((1, *vec.single_action_space.shape), np.float32)
    rates: dict[bool, list[float]] = {False: [], True: []}
    try:
        for seed in range(3):
            for render in (False, True):
                vec.reset(seed=[1000 + seed])
                start = time.perf_counter()
                for _ in range(steps - 1):
                    vec.step(action)
                    if render:
                        vec.call("render")
                rates[render].append((steps - 1) / (time.perf_counter() - start))
    finally:
        vec.close()
    return statistics.median(rates[False]), statistics.median(rates[True])


def measure(quick: bool = False) -> dict[str, float]:
    with tempfile.TemporaryDirectory(prefix="bench_lerobot_") as tmp:
        work = Path(tmp)
        (work / "record").mkdir()
        (work / "eval").mkdir()
        hz = record_hz(work / "record", episodes=2 if quick else 3, seconds=3.0 if quick else 5.0)
        lerobot_rate, teleop_rate = eval_rates(work / "eval", episodes=2 if quick else 5, steps=60 if quick else 150)
    env_rate, render_rate = env_rates(60 if quick else 150)
    return {"lerobot_record_hz": round(hz, 2), "lerobot_eval_steps_s": round(lerobot_rate, 1),
            "teleop_eval_steps_s": round(teleop_rate, 1), "lerobot_eval_vs_teleop_eval": round(lerobot_rate / teleop_rate, 3),
            "lerobot_env_steps_s": round(env_rate, 1), "lerobot_env_render_steps_s": round(render_rate, 1)}
