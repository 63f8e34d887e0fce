"""Policies that drive a `TeleopEnv`: the one interface `teleop eval` runs, and two kinds of it.

    policy = LeRobotPolicy.load("outputs/act_lift/checkpoints/last/pretrained_model", device="cpu")
    policy.attach(env)             # checks the features fit (PolicyMismatch naming the one that does not)
    policy.reset()                 # before each episode
    action = policy.select_action(observation)   # the env's action vector

`LeRobotPolicy` is a LeRobot pretrained-model folder (what `lerobot-train` writes under
`checkpoints/<step>/pretrained_model`), loaded with LeRobot's own policy factory and
pre/post-processors. `ScriptedPolicy` plays a scenes/scripts JSON through EE actions,
with the script's privileged view of the scene (where the cube is): it is how the
evaluation's success detection and action conversion are checked.

LeRobot and torch are optional (the `lerobot`/`train` extras): imported lazily, in
`LeRobotPolicy.load` only.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

import numpy as np

from devices.command import Command
from devices.script import ScriptDevice
from replay.features import rotation_vector, is_channel_first
from scenes.errors import TeleopError

if TYPE_CHECKING:  # annotations only
    from teleop.learn.gym_env import Observation, TeleopEnv

IMAGE_PREFIX = "observation.images."
CONFIG_NAME = "config.json"
TRAIN_CONFIG_NAME = "train_config.json"
DEVICES = ("cpu", "cuda", "mps")


class PolicyError(TeleopError):
    """A policy cannot be loaded (a missing folder, not a LeRobot model, no such device)."""


class PolicyMismatch(PolicyError):
    """The policy's input or output features do not match the environment's; the message names the feature."""


@runtime_checkable
class Policy(Protocol):
    """Anything that maps the env's observations to its actions, one control tick at a time."""

    name: str  # what episode files record as `policy` (a path for a checkpoint)

    def attach(self, env: "TeleopEnv") -> None:
        """Check this policy fits `env` (raise PolicyMismatch naming the feature) and bind to it."""
        ...

    def reset(self) -> None:
        """Forget the last episode (action queues, a script's progress)."""
        ...

    def select_action(self, observation: "Observation") -> np.ndarray:
        """The action vector for this tick, in the env's action layout."""
        ...


@dataclass(frozen=True)
class TrainedOn:
    """What a checkpoint says about the environment it was trained for."""

    cameras: tuple[str, ...]  # feature keys of its image inputs, observation.images.<camera>
    image_size: tuple[int, int] | None  # (width, height) of its images; None: no images
    action: str | None  # action mode of its training data (None: unknown, the dataset is not here)
    fps: float | None  # frames per second of its training data (None: unknown)
    robot: str | None  # robot_type of its training data (None: unknown)
    names: dict[str, list[str]]  # feature -> entry names, from the training data (empty: unknown)


def _shape(value: Any) -> tuple[int, ...]:
    return tuple(int(v) for v in value)


def _chw(feature: dict) -> tuple[int, ...]:
    """An env image feature's shape as a policy declares images: (3, H, W)."""
    shape = _shape(feature["shape"])
    return shape if is_channel_first(feature) else (shape[2], shape[0], shape[1])


def action_mode_of(names: Sequence[str]) -> str | None:
    """The export's action mode from an action feature's entry names (None: not one of ours)."""
    names = [n.split(".")[-1] for n in names]  # bimanual names carry an arm prefix
    if "qw" in names:
        return "ee_pose"
    if "drx" in names:
        return "ee_delta"
    return "joint" if names else None


def check_features(inputs: dict[str, tuple[int, ...]], outputs: dict[str, tuple[int, ...]],
                   env_features: dict, names: dict[str, list[str]] | None = None, where: str = "") -> None:
    """Every policy input must be one of the env's features with the same shape (images compared
    channel-first), the output `action` the env's action; names too where the training data is known."""
    def env_shape(key: str) -> tuple[int, ...]:
        feature = env_features[key]
        return _chw(feature) if key.startswith(IMAGE_PREFIX) else _shape(feature["shape"])

    for key, shape in [*inputs.items(), *outputs.items()]:
        kind = "output" if key in outputs else "input"
        if key not in env_features:
            have = ", ".join(k for k in env_features if k != "action" or kind == "output")
            raise PolicyMismatch(f"policy {kind} {key} {list(shape)} is not in the environment{where} (it has {have})")
        if env_shape(key) != shape:
            raise PolicyMismatch(f"policy {kind} {key} has shape {list(shape)}, the environment's{where} is {list(env_shape(key))}")
    if "action" not in outputs:
        raise PolicyMismatch(f"policy outputs {', '.join(outputs) or 'nothing'}, not the environment's action")
    for key, wanted in (names or {}).items():
        if key in env_features and key in {**inputs, **outputs} and not key.startswith(IMAGE_PREFIX):
            have = list(env_features[key].get("names") or [])
            if have and list(wanted) != have:
                raise PolicyMismatch(f"policy feature {key} is {', '.join(wanted)}; the environment's{where} is {', '.join(have)}")


# --- LeRobot checkpoints ---------------------------------------------------------------


def _read_json(path: Path) -> dict:
    try:
        return json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise PolicyError(f"{path}: cannot read ({exc.__class__.__name__})") from None


def _training_info(folder: Path) -> dict | None:
    """The training dataset's meta/info.json, where train_config.json names a dataset that is here."""
    train = folder / TRAIN_CONFIG_NAME
    if not train.is_file():
        return None
    try:
        dataset = json.loads(train.read_text()).get("dataset") or {}
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return None
    root = dataset.get("root")
    candidates = [Path(root).expanduser()] if root else []
    if dataset.get("repo_id"):  # LeRobot's default home for a dataset without a root (HF_LEROBOT_HOME)
        home = os.environ.get("HF_LEROBOT_HOME") or Path(os.environ.get("HF_HOME") or Path.home() / ".cache" / "huggingface") / "lerobot"
        candidates.append(Path(home).expanduser() / dataset["repo_id"])
    for candidate in candidates:
        info = candidate / "meta" / "info.json"
        if info.is_file():
            try:
                return json.loads(info.read_text())
            except (OSError, UnicodeDecodeError, json.JSONDecodeError):
                return None
    return None


def read_checkpoint(folder: str | Path) -> tuple[dict, dict | None]:
    """(config.json, the training dataset's info.json or None), with one-line errors for a bad folder."""
    folder = Path(folder)
    if not folder.exists():
        raise PolicyError(f"{folder}: no such policy folder (lerobot-train writes one under OUTPUT/checkpoints/<step>/pretrained_model)")
    if not folder.is_dir():
        raise PolicyError(f"{folder}: is not a folder (give a LeRobot pretrained_model folder)")
    if not (folder / CONFIG_NAME).is_file():
        raise PolicyError(f"{folder}: not a LeRobot pretrained-model folder (no {CONFIG_NAME}; lerobot-train writes one under "
                          "OUTPUT/checkpoints/<step>/pretrained_model)")
    config = _read_json(folder / CONFIG_NAME)
    features = [config.get("input_features"), config.get("output_features")]
    if not isinstance(config.get("type"), str) or not all(isinstance(f, dict) for f in features):
        raise PolicyError(f"{folder / CONFIG_NAME}: not a LeRobot policy config (no type, input_features or output_features)")
    return config, _training_info(folder)


def trained_on(config: dict, info: dict | None) -> TrainedOn:
    """What the checkpoint's config (and its training data, where found) say about its environment."""
    inputs = {k: _shape(v["shape"]) for k, v in config["input_features"].items()}
    images = {k: s for k, s in inputs.items() if k.startswith(IMAGE_PREFIX)}
    sizes = {(s[2], s[1]) if s[0] == 3 else (s[1], s[0]) for s in images.values() if len(s) == 3}
    if len(sizes) > 1:
        raise PolicyMismatch(f"policy images differ in size ({', '.join(f'{k} {list(s)}' for k, s in images.items())}); "
                             "the environment renders every camera at one size")
    features = (info or {}).get("features") or {}
    names = {k: list(v["names"]) for k, v in features.items()
             if isinstance(v, dict) and isinstance(v.get("names"), list) and not k.startswith(IMAGE_PREFIX)}
    return TrainedOn(
        cameras=tuple(images),
        image_size=next(iter(sizes), None),
        action=action_mode_of(names["action"]) if "action" in names else None,
        fps=float(info["fps"]) if info and info.get("fps") else None,
        robot=(info or {}).get("robot_type"),
        names=names,
    )


class Checkpoint:
    """A LeRobot pretrained-model folder as read from its JSON files (no torch): what it takes and gives."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.config, info = read_checkpoint(self.path)
        self.trained_on = trained_on(self.config, info)
        self.inputs = {k: _shape(v["shape"]) for k, v in self.config["input_features"].items()}
        self.outputs = {k: _shape(v["shape"]) for k, v in self.config["output_features"].items()}

    def env_options(self) -> dict[str, Any]:
        """The TeleopEnv options this checkpoint implies: image size, and action mode and rate where known."""
        t = self.trained_on
        options: dict[str, Any] = {}
        if t.image_size is not None:
            options["image_size"] = t.image_size
        if t.action is not None:
            options["action"] = t.action
        if t.fps is not None:
            options["control_hz"] = t.fps
        return options

    def check(self, env: "TeleopEnv") -> None:
        """PolicyMismatch naming the first feature that does not fit `env`."""
        env = env.unwrapped
        where = f" ({env.session.scene_name}, {env.session.robot.name}, {env.action_mode} actions)"
        check_features(self.inputs, self.outputs, env.features, self.trained_on.names, where)


class LeRobotPolicy:
    """A LeRobot pretrained-model folder, run with its own pre/post-processors."""

    def __init__(self, checkpoint: Checkpoint, policy: Any, preprocessor: Any, postprocessor: Any, device: str) -> None:
        self.checkpoint = checkpoint
        self.path = checkpoint.path
        self.name = str(checkpoint.path.resolve())  # what recorded rollouts store as `policy`
        self.device = device
        self._policy = policy
        self._pre = preprocessor
        self._post = postprocessor
        self.task = ""
        self.robot_type = checkpoint.trained_on.robot or ""

    @classmethod
    def load(cls, path: str | Path | Checkpoint, device: str = "cpu") -> "LeRobotPolicy":
        """Load with LeRobot's factory (get_policy_class + make_pre_post_processors) onto `device`."""
        if device not in DEVICES:
            raise PolicyError(f"device {device!r}: choose one of {', '.join(DEVICES)}")
        checkpoint = path if isinstance(path, Checkpoint) else Checkpoint(path)
        path = checkpoint.path
        # Optional heavy dependencies (the lerobot extra): imported only when a checkpoint is loaded.
        try:
            import torch
            from lerobot.configs.policies import PreTrainedConfig
            from lerobot.policies.factory import get_policy_class, make_pre_post_processors
        except ImportError as exc:
            raise PolicyError(f"running a LeRobot policy needs LeRobot and torch (pip install -e '.[train]'): {exc}") from None
        if device == "cuda" and not torch.cuda.is_available():
            raise PolicyError("--device cuda: no CUDA GPU is available to torch here (use --device cpu)")
        if device == "mps" and not torch.backends.mps.is_available():
            raise PolicyError("--device mps: Apple's MPS is not available here (use --device cpu)")
        try:  # LeRobot prints "Loading weights from local directory" to stdout: dropped, stdout is the report's
            with contextlib.redirect_stdout(io.StringIO()):
                cfg = PreTrainedConfig.from_pretrained(str(path))
                cfg.device = device
                cfg.pretrained_path = path
                policy = get_policy_class(cfg.type).from_pretrained(str(path), config=cfg)
            policy.to(device)
            policy.eval()
            pre, post = make_pre_post_processors(
                cfg, pretrained_path=str(path), preprocessor_overrides={"device_processor": {"device": device}},
                postprocessor_overrides={"device_processor": {"device": "cpu"}},
            )
        except (ValueError, KeyError, OSError, ImportError, RuntimeError) as exc:
            first = str(exc).strip().splitlines()[0] if str(exc).strip() else exc.__class__.__name__
            raise PolicyError(f"{path}: LeRobot cannot load this policy: {first}") from None
        return cls(checkpoint, policy, pre, post, device)

    @property
    def trained_on(self) -> TrainedOn:
        return self.checkpoint.trained_on

    def env_options(self) -> dict[str, Any]:
        return self.checkpoint.env_options()

    def attach(self, env: "TeleopEnv") -> None:
        self.checkpoint.check(env)
        self.task = env.unwrapped.session.scene.instruction

    def reset(self) -> None:
        self._policy.reset()

    def select_action(self, observation: "Observation") -> np.ndarray:
        import torch  # optional heavy dependency, loaded with the checkpoint
        from lerobot.policies.utils import prepare_observation_for_inference

        frame = {k: np.array(observation[k]) for k in self.checkpoint.inputs}
        batch = prepare_observation_for_inference(frame, torch.device(self.device), self.task, self.robot_type)
        with torch.inference_mode():
            action = self._post(self._policy.select_action(self._pre(batch)))
        return np.asarray(action.squeeze(0).detach().cpu().numpy(), dtype=np.float64)


# --- a scripted policy -----------------------------------------------------------------


class ScriptedPolicy:
    """Plays a scenes/scripts JSON as EE actions (ee_pose or ee_delta), holding the last target at its end.

    It reads the scene as a script does (where a body is), which a learned policy
    cannot: it proves that the evaluation converts actions and detects success.
    """

    def __init__(self, script: str | Path) -> None:
        self.script = ScriptDevice(script)
        self.name = f"script:{Path(script).name}"
        self._env: "TeleopEnv | None" = None
        self._targets: list[tuple[np.ndarray, np.ndarray]] = []
        self._grippers: list[float] = []

    def attach(self, env: "TeleopEnv") -> None:
        env = env.unwrapped
        if env.action_mode not in ("ee_pose", "ee_delta"):
            raise PolicyMismatch(f"a scripted policy gives EE actions (ee_pose or ee_delta), not {env.action_mode}")
        self._env = env

    def reset(self) -> None:
        if self._env is None:
            raise PolicyError("attach the policy to an environment first")
        session = self._env.session
        self.script.check(session.controller)  # every name it uses, before the episode's first step
        self.script.restart()
        self._targets = [tuple(np.array(v) for v in session.controller.target_pose(k)) for k in range(session.controller.n_arms)]
        self._grippers = [1.0] * session.controller.n_arms

    def _apply(self, command: Command) -> None:
        pos, quat = self._targets[command.arm]
        if command.target_pos is not None:
            pos = np.array(command.target_pos, dtype=float)
        if command.target_quat is not None:
            quat = np.array(command.target_quat, dtype=float)
        self._targets[command.arm] = (pos, quat)
        if command.gripper in ("open", "close"):
            self._grippers[command.arm] = 1.0 if command.gripper == "open" else 0.0

    def select_action(self, observation: "Observation") -> np.ndarray:
        env = self._env
        if env is None:
            raise PolicyError("attach the policy to an environment first")
        session = env.session
        if not self.script.finished:
            for command in self.script.poll(session.controller, session.dt):
                self._apply(command)
        parts: list[np.ndarray] = []
        for k, arm in enumerate(env.arms):
            pos, quat = self._targets[k]
            if env.action_mode == "ee_pose":
                parts += [pos, quat]
            else:  # ee_delta: target minus the actual EE pose, in the world frame
                ee_pos, ee_quat = session.controller.ee_pose(k)
                parts += [pos - ee_pos, rotation_vector(quat, ee_quat)]
            if arm.gripper_id is not None:
                parts.append(np.array([self._grippers[k]]))
        return np.concatenate(parts)


__all__ = ["Checkpoint", "LeRobotPolicy", "Policy", "PolicyError", "PolicyMismatch", "ScriptedPolicy",
           "TrainedOn", "action_mode_of", "check_features", "read_checkpoint", "trained_on"]
