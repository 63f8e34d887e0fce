"""Compose robot + arena + task into one model, the same way every time for a seed.

The model is compiled from the very XML string that recordings store (with
the mesh/texture bytes as assets), so a replay compiles the identical model.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import mujoco
import numpy as np

from scenes.assembly.arena import TABLE_TOP, Layout, frame_cameras, make_arena, yaw_quat
from scenes.errors import first_line
from scenes.assembly.framing import work_points
from scenes.assembly.robot import ArmSpec, RobotSpec, SceneError, load_robot
from scenes.tasks.registry import Task, find_task
from scenes.vary.variation import Variation, physics_rng, task_ranges
from scenes.vary.physics import vary_physics


@dataclass
class Scene:
    """A compiled scene: model, its XML and assets, the arms (with final names) and the task."""

    task: Task
    robot: RobotSpec
    arms: tuple[ArmSpec, ...]
    seed: int
    xml: str
    assets: dict[str, bytes]
    model: mujoco.MjModel
    layout: Layout
    cameras: tuple[str, ...] = field(default=())
    variation: dict = field(default_factory=dict)  # the physics drawn for this seed (empty: none); episodes record it

    def make_data(self) -> mujoco.MjData:
        """Fresh MjData at the seeded layout with every arm at home."""
        data = mujoco.MjData(self.model)
        self.reset_data(data)
        return data

    def reset_data(self, data: mujoco.MjData) -> None:
        mujoco.mj_resetData(self.model, data)
        for arm in self.arms:
            for name, value in zip(arm.joints, arm.home):
                data.qpos[self.model.joint(name).qposadr[0]] = value
                act = actuator_for_joint(self.model, name)
                if act is not None:
                    data.ctrl[act] = value
            if arm.gripper is not None:
                data.ctrl[self.model.actuator(arm.gripper.actuator).id] = arm.gripper.open
        for name, value in self.task.initial_joints().items():
            data.qpos[self.model.joint(name).qposadr[0]] = value
        mujoco.mj_forward(self.model, data)

    def success(self, data: mujoco.MjData) -> bool:
        return self.task.success(self.model, data)

    def observe(self, data: mujoco.MjData) -> bool | None:
        """Called after every control tick: a task with a `hold` times how long its success has held.

        Returns that tick's success when it judged it (a `hold`), else None."""
        if self.task.hold > 0:
            return bool(self.task.success(self.model, data))
        return None

    def observer(self, data: mujoco.MjData) -> Callable[[], bool] | None:
        """`observe(data)` bound once, for a controller's every tick: None when the task has no `hold`
        (nothing to time), else a call that judges and times it (cheaper than `observe`: nothing looked up)."""
        timer = getattr(self.task, "timer", None)
        if timer is not None:
            return timer(self.model, data)
        return (lambda: bool(self.task.success(self.model, data))) if self.task.hold > 0 else None

    @property
    def instruction(self) -> str:
        """The task's instruction for this seed (one of its paraphrases; episodes store it as `task`)."""
        return self.task.instruction_for(self.seed)[0]


def actuator_for_joint(model: mujoco.MjModel, joint: str) -> int | None:
    """The actuator that drives `joint` directly (every arm joint has one after building)."""
    jid = model.joint(joint).id
    for i in range(model.nu):
        if model.actuator_trntype[i] == mujoco.mjtTrn.mjTRN_JOINT and model.actuator_trnid[i, 0] == jid:
            return i
    return None


def layout_for(robot: RobotSpec) -> Layout:
    """Where `robot`'s tasks happen: the workspace centre, placement spread and cube size, from its reach."""
    size = robot.object_size
    if robot.bimanual:
        half_gap = abs(robot.mounts[0].pos[0])
        return Layout(center=(0.0, 0.0), spread=0.25 * half_gap, size=size,
                      table_half=(half_gap + 0.2, 0.6), table_center=(0.0, 0.0), bimanual=True, reach=robot.reach)
    reach = robot.reach
    center = (0.55 * reach, 0.0)
    return Layout(center=center, spread=0.18 * reach, size=size,
                  table_half=(0.5 * reach + 0.35, 0.7 * reach + 0.1), table_center=(0.5 * reach - 0.1, 0.0), bimanual=False, reach=reach)


def _inline_assets(spec: mujoco.MjSpec, base_dir: Path) -> dict[str, bytes]:
    """Read every file the robot's MJCF references into an assets dict.

    The files are renamed to unique flat names so that the stored XML and the
    assets dict alone rebuild the model anywhere.
    """
    assets: dict[str, bytes] = {}
    meshdir = base_dir / (spec.meshdir or "")
    texdir = base_dir / (spec.texturedir or "")

    def take(file: str, folder: Path, what: str) -> str:
        path = Path(file)
        if not path.is_absolute():
            path = folder / path
        if not path.is_file():
            raise SceneError(f"{what} file {path} not found (paths are relative to the robot's MJCF folder)")
        name = f"{len(assets):03d}_{path.name}"
        assets[name] = path.read_bytes()
        return name

    for mesh in spec.meshes:
        if mesh.file:
            mesh.file = take(mesh.file, meshdir, "mesh")
    for tex in spec.textures:
        if tex.file:
            tex.file = take(tex.file, texdir, "texture")
    for hfield in spec.hfields:
        if hfield.file:
            hfield.file = take(hfield.file, base_dir, "hfield")
    spec.meshdir = ""
    spec.texturedir = ""
    spec.assets = dict(assets)  # so the spec compiles on its own too
    return assets


def _load_robot_spec(robot: RobotSpec) -> tuple[mujoco.MjSpec, dict[str, bytes], tuple[ArmSpec, ...]]:
    """Load the robot MJCF; for a user's robot, check names and add missing actuators."""
    try:
        spec = mujoco.MjSpec.from_file(str(robot.mjcf))
    except Exception as exc:  # mujoco raises ValueError with a multi-line message
        first = first_line(exc)
        raise SceneError(f"{robot.mjcf}: MJCF does not load: {first}") from None
    assets = _inline_assets(spec, robot.mjcf.parent)
    arms = robot.arms
    if not robot.builtin:
        arms = tuple(_prepare_user_arm(spec, robot, arm) for arm in arms)
    for key in list(spec.keys):
        spec.delete(key)
    _stiffen_joint_limits(spec, arms)
    return spec, assets, arms


def _stiffen_joint_limits(spec: mujoco.MjSpec, arms: tuple[ArmSpec, ...]) -> None:
    """Hard joint stops: MuJoCo's default limits are soft enough to be pushed past
    by a fast arm's own inertia; a robot's range is a promise."""
    names = {j for arm in arms for j in arm.joints}
    for joint in spec.joints:
        if joint.name in names:
            joint.solref_limit = [0.004, 1.0]
            joint.solimp_limit = [0.99, 0.999, 0.001, 0.5, 2.0]


def _prepare_user_arm(spec: mujoco.MjSpec, robot: RobotSpec, arm: ArmSpec) -> ArmSpec:
    where = robot.extra.get("toml", robot.name)
    try:
        probe = spec.copy().compile()
    except Exception as exc:
        first = first_line(exc)
        raise SceneError(f"{where}: MJCF does not compile: {first}") from None
    if mujoco.mj_name2id(probe, mujoco.mjtObj.mjOBJ_SITE, arm.ee_site) < 0:
        sites = [probe.site(i).name for i in range(probe.nsite)]
        raise SceneError(f"{where}: ee_site '{arm.ee_site}' is not a site in the model (sites: {', '.join(sites) or 'none'})")
    for joint in arm.joints:
        jid = mujoco.mj_name2id(probe, mujoco.mjtObj.mjOBJ_JOINT, joint)
        if jid < 0:
            raise SceneError(f"{where}: joint '{joint}' is not in the model")
        if int(probe.jnt_type[jid]) not in (int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE)):
            raise SceneError(f"{where}: joint '{joint}' is not a hinge or slide joint")
    if arm.gripper is not None and mujoco.mj_name2id(probe, mujoco.mjtObj.mjOBJ_ACTUATOR, arm.gripper.actuator) < 0:
        raise SceneError(f"{where}: gripper actuator '{arm.gripper.actuator}' is not in the model")

    home = arm.home
    if not home:
        key_name = robot.extra.get("home_key", "home")
        kid = mujoco.mj_name2id(probe, mujoco.mjtObj.mjOBJ_KEY, key_name)
        if kid < 0:
            raise SceneError(f"{where}: home keyframe '{key_name}' is not in the model")
        home = tuple(float(probe.key_qpos[kid, probe.joint(j).qposadr[0]]) for j in arm.joints)

    # Give every arm joint a position actuator: replace motors (or nothing) on them.
    kp = robot.extra.get("kp", 300.0)
    forcerange = robot.extra.get("forcerange")
    joint_ids = {probe.joint(j).id: j for j in arm.joints}
    for i in range(probe.nu):
        if probe.actuator_trntype[i] == mujoco.mjtTrn.mjTRN_JOINT and probe.actuator_trnid[i, 0] in joint_ids:
            is_position = (probe.actuator_biastype[i] == mujoco.mjtBias.mjBIAS_AFFINE and probe.actuator_gainprm[i, 0] > 0
                           and probe.actuator_biasprm[i, 1] < 0)
            if not is_position:
                spec.delete(spec.actuators[i])
                probe = None  # indices shift; recount below
                break
    if probe is None:
        return _prepare_user_arm(spec, robot, arm)
    for joint in arm.joints:
        jid = probe.joint(joint).id
        has = any(probe.actuator_trntype[i] == mujoco.mjtTrn.mjTRN_JOINT and probe.actuator_trnid[i, 0] == jid for i in range(probe.nu))
        if has:
            continue
        act = spec.add_actuator(name=f"{joint}_position", target=joint, trntype=mujoco.mjtTrn.mjTRN_JOINT)
        act.set_to_position(kp=kp, dampratio=1.0)
        if probe.jnt_limited[jid]:
            act.ctrlrange = probe.jnt_range[jid]
            act.ctrllimited = 1
        if forcerange:
            act.forcerange = [-forcerange, forcerange]
            act.forcelimited = 1
    for body in spec.bodies[1:]:
        body.gravcomp = 1.0
    return ArmSpec(ee_site=arm.ee_site, joints=arm.joints, home=home, gripper=arm.gripper,
                   orientation_cost=arm.orientation_cost, hand_bodies=arm.hand_bodies)


def _user_reach(spec: mujoco.MjSpec, arm: ArmSpec) -> float:
    """Estimate a user robot's reach: the longest base-to-EE distance over random poses."""
    model = spec.copy().compile()
    data = mujoco.MjData(model)
    rng = np.random.default_rng(0)
    site = model.site(arm.ee_site).id
    adr = [model.joint(j).qposadr[0] for j in arm.joints]
    ids = [model.joint(j).id for j in arm.joints]
    base = None
    best = 0.0
    for _ in range(200):
        for a, j in zip(adr, ids):
            lo, hi = model.jnt_range[j] if model.jnt_limited[j] else (-math.pi, math.pi)
            data.qpos[a] = rng.uniform(lo, hi)
        mujoco.mj_kinematics(model, data)
        if base is None:
            base = data.xpos[model.body(model.jnt_bodyid[ids[0]]).id].copy()
        best = max(best, float(np.linalg.norm(data.site_xpos[site] - base)))
    return 0.85 * best


def build_scene(task: str | Path | Task, robot: str | Path | RobotSpec, seed: int = 0, timestep: float = 0.002,
                variation: Variation | None = None) -> Scene:
    """Compile `task` (a name, a task file PATH.toml or a Task) with `robot`, objects placed from `seed` (same seed, same scene).

    variation: physics kinds to draw for `seed` (scenes.vary.physics) into the model; looks are not drawn here.
    """
    if isinstance(robot, (str, Path)):
        robot = load_robot(robot)
    task = find_task(task)
    if not task.supports(robot.bimanual):
        kind = "bimanual" if robot.bimanual else "single-arm"
        raise SceneError(f"scene '{task.name}' does not work with the {kind} robot '{robot.name}'")

    robot_spec, assets, arms = _load_robot_spec(robot)
    if not robot.builtin and robot.reach <= 0:
        from dataclasses import replace

        robot = replace(robot, reach=_user_reach(robot_spec, arms[0]))
    layout = layout_for(robot)
    if robot.bimanual:
        arena = make_arena(layout, timestep)
        final_arms = []
        for arm, mount in zip(arms, robot.mounts):
            frame = arena.worldbody.add_frame(pos=[mount.pos[0], mount.pos[1], TABLE_TOP + mount.pos[2]], quat=yaw_quat(mount.yaw))
            arena.attach(robot_spec.copy(), prefix=mount.prefix, frame=frame)
            final_arms.append(arm.prefixed(mount.prefix))
        arms = tuple(final_arms)
    else:
        arena = make_arena(layout, timestep, robot_spec)
    before = {b.name for b in arena.worldbody.bodies}  # the robots' roots; the task adds its own
    task_assets = task.build(arena, layout, np.random.default_rng(seed)) or {}
    drawn = _vary(arena, task, before, seed, variation) if variation is not None and variation.physics else {}
    assets = {**assets, **task_assets}

    try:
        probe = arena.compile()
    except Exception as exc:
        raise SceneError(f"scene '{task.name}' with robot '{robot.name}' does not compile: {first_line(exc)}") from None
    frame_cameras(arena, layout, work_points(task, layout, probe))  # where this task's objects start and its goals lie
    try:
        # to_xml keeps 6 digits; the timestep must be exact so that the control
        # period is exactly substeps * timestep.
        xml = re.sub(r'(<option[^>]*?timestep=")[^"]*(")', rf"\g<1>{timestep!r}\g<2>", arena.to_xml(), count=1)
        model = mujoco.MjModel.from_xml_string(xml, assets)
    except Exception as exc:
        first = first_line(exc)
        raise SceneError(f"scene '{task.name}' with robot '{robot.name}' does not compile: {first}") from None
    cameras = tuple(model.camera(i).name for i in range(model.ncam))
    return Scene(task=task, robot=robot, arms=arms, seed=seed, xml=xml, assets=assets, variation=drawn,
                 model=model, layout=layout, cameras=cameras)


def _vary(arena: mujoco.MjSpec, task: Task, robot_roots: set[str], seed: int, variation: Variation) -> dict:
    """Draw and apply the physics of `variation` for `seed`; what an episode records of it."""
    roots = [b.name for b in arena.worldbody.bodies if b.name not in robot_roots]
    ranges = variation.ranges(task_ranges(task))
    try:
        params = vary_physics(arena, roots, sorted(robot_roots), variation.physics, ranges, physics_rng(seed, variation.split))
    except ValueError as exc:  # mujoco's compile errors, multi-line
        raise SceneError(f"scene '{task.name}' does not compile with its physics varied: {first_line(exc)}") from None
    return {"kinds": list(variation.physics), "split": variation.split, "seed": int(seed),
            "ranges": {k: v for k, v in ranges.to_json().items() if k in ("size", "mass", "friction", "damping", "distractors",
                                                                          "distractor_size")},
            "params": params}
