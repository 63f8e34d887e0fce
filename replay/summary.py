"""What `teleop inspect` shows of an episode: what the file holds, without compiling the model,
with who drove it and its stored subtasks.
"""

from __future__ import annotations

import numpy as np

from replay.episode import CONTROL_POLICY, Episode
from replay.review.listing import inspect_quality
from replay.subtasks.sidecar import AnnotationError, read_subtasks


def summarize(episode: Episode) -> dict:
    """The `teleop inspect` object: what the file holds, without compiling the model."""
    m = episode.meta
    if episode.steps:
        err = np.linalg.norm(episode.ee_target[:, :, :3] - episode.ee_pose[:, :, :3], axis=-1) * 1000.0
        tracking = {"median": round(float(np.median(err)), 3), "max": round(float(np.max(err)), 3)}
    else:
        tracking = {"median": None, "max": None}
    return {
        "path": str(episode.path),
        "format": episode.format,
        "steps": episode.steps,
        "seconds": round(episode.seconds, 6),
        "success": m.success,
        "complete": m.complete,
        "truncated": episode.truncated,
        "robot": m.robot,
        "scene": m.scene,
        "seed": m.seed,
        "task": m.task,
        "mujoco_version": m.mujoco_version,
        "machine": m.machine,
        "platform": m.platform,
        "control_hz": m.control_hz,
        "timestep": m.timestep,
        "substeps": m.substeps,
        "n_arms": m.n_arms,
        "nstate": m.nstate,
        "start_time": m.start_time,
        "episode_index": m.episode_index,
        "schema_version": m.schema_version,
        "steps_with_commands": sum(1 for c in episode.commands if c),
        "ee_tracking_error_mm": tracking,
        "source": m.source,
        "devices": list(m.devices),
        "source_episodes": list(m.source_episodes),
        "generator": dict(m.generator) if m.generator else None,
        "policy": m.policy,
        "operator": m.operator,  # a collection campaign's episodes: who, in which campaign and session (else None)
        "campaign": m.campaign,
        "session": m.session,
        "control": _control(episode),
        "subtasks": _subtasks(episode),
        "variation": m.extra.get("variation"),  # the physics it was generated with (scenes.vary.variation), or None
        "quality": inspect_quality(episode),  # flags and scores (replay.review.quality); this part compiles the model
    }


def _control(episode: Episode) -> dict | None:
    """Who drove (None: the episode does not record it): steps by the policy and by a person, and takeovers."""
    control = episode.control
    if control is None:
        return None
    by_policy = control == CONTROL_POLICY
    return {
        "policy_steps": int(by_policy.sum()),
        "operator_steps": int((~by_policy).sum()),
        "takeovers": int(np.count_nonzero(by_policy[:-1] & ~by_policy[1:])),
    }


def _subtasks(episode: Episode) -> list[dict] | None:
    """The episode's stored subtask annotations (None: not annotated, or made for another length)."""
    try:
        found = read_subtasks(episode.path, episode.steps)
    except AnnotationError:
        return None
    return None if found is None else [s.to_json() for s in found]
