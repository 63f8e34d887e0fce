"""Near-miss grasps: how fast a closing gripper can throw a cube it catches by the edge.

Figures (`measure`):
  grasp_edge_max_object_speed   m/s, the largest linear speed of the cube (world frame, its centre)
                                while the gripper closes on its edge, over every robot and SEEDS seeds
                                of the built-in `lift`; a person's hand moves at up to ~0.5 m/s, so a
                                closing gripper should push the cube no faster than that
  grasp_edge_max_speed_<robot>  the same, per robot

One near miss (`near_miss_speed`): the hand comes down over the cube with its grasp point moved
sideways (across the fingers, not along their closing line) so that the pads overlap the cube by
10-90 % of their width, the hand turned up to 0.8 rad (46 deg) about the vertical so that a pad may
meet a corner, and its height between 0.3 half-sizes under the cube's centre and one over (`draw_miss`);
then the gripper closes for CLOSE_S while the arm holds still. The control rate is 500 Hz (one physics
step per tick) so that the speed is sampled at every physics step.
"""

from __future__ import annotations

import sys

import mujoco
import numpy as np

from devices.command import Command

ROBOTS = ("panda", "ur5e", "so101", "bimanual")
SEEDS = 40  # near misses per robot (the bench figure)
QUICK_SEEDS = 4  # --quick (the test): the worst near misses of the 40 are among seeds 0-3 for ur5e and the two-arm rig
CONTROL_HZ = 500.0  # one physics step per tick: speeds seen at every step
ABOVE = 0.08  # m above the grasp height where the hand lines up
CLOSE_S = 1.0  # s of closing watched (the scripts give a close 0.6 s)
HAND_SPEED = 0.5  # m/s: the goal, a person's hand


def _axis_extent(model: mujoco.MjModel, data: mujoco.MjData, geom: int, axis: np.ndarray) -> float:
    """Half-extent (m) of `geom`'s bounding box along world `axis`."""
    rot = data.geom_xmat[geom].reshape(3, 3)
    return float(np.abs(rot.T @ axis) @ model.geom_aabb[geom, 3:])


def _pads(model: mujoco.MjModel, prefix: str) -> list[int]:
    """The arm's finger pads: geoms named `<prefix>...pad` (every built-in gripper names its two so)."""
    out = []
    for g in range(model.ngeom):
        name = model.geom(g).name
        if name.startswith(prefix) and name.endswith("pad") and "/" not in name[len(prefix):]:
            out.append(g)
    if len(out) != 2:
        raise RuntimeError(f"expected two finger pads under {prefix!r}, found {len(out)}")
    return out


def _go(session, pos: np.ndarray, quat: np.ndarray, seconds: float, gripper: str | None = None) -> None:
    """Move the arm-0 target from where it is to `pos`/`quat` linearly over `seconds`."""
    start, _ = session.controller.target_pose(0)
    ticks = max(1, int(round(seconds * CONTROL_HZ)))
    for k in range(1, ticks + 1):
        s = k / ticks
        session.step([Command(target_pos=start + s * (pos - start), target_quat=quat, gripper=gripper if k == 1 else None)])


def draw_miss(seed: int) -> tuple[float, float, float, float]:
    """(overlap: the pads' width on the cube, 0-1; side: +-1; yaw: rad about the vertical; height: of the cube's, -1..1) for `seed`."""
    rng = np.random.default_rng(10_000 + seed)
    return float(rng.uniform(0.1, 0.9)), float(rng.choice([-1.0, 1.0])), float(rng.uniform(-0.8, 0.8)), float(rng.uniform(-0.3, 1.0))


def near_miss_speed(robot: str, seed: int, miss: tuple[float, float, float, float] | None = None) -> float:
    """Largest cube speed (m/s) while `robot`'s gripper closes on the cube's edge, layout and miss drawn from `seed`."""
    import teleop

    overlap, side, yaw, height = miss if miss is not None else draw_miss(seed)
    session = teleop.Session(scene="lift", robot=robot, seed=seed, control_hz=CONTROL_HZ)
    model, data = session.controller.model, session.controller.data
    arm = session.controller.scene.arms[0]
    prefix = arm.ee_site[: arm.ee_site.rfind("/") + 1]
    pads = _pads(model, prefix)
    cube = model.body("cube").id
    cube_geom = int(model.body_geomadr[cube])
    dof = int(model.jnt_dofadr[model.body_jntadr[cube]])

    _, home_quat = session.controller.target_pose(0)
    turn = np.array([np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)])
    quat = np.empty(4)
    mujoco.mju_mulQuat(quat, turn, home_quat)
    cube_pos = data.xpos[cube].copy()
    grasp_z = cube_pos[2] + height * _axis_extent(model, data, cube_geom, np.array([0.0, 0.0, 1.0]))  # 0: the lift script's
    _go(session, np.array([cube_pos[0], cube_pos[1], grasp_z + ABOVE]), quat, 1.2, gripper="open")
    _go(session, np.array([cube_pos[0], cube_pos[1], grasp_z + ABOVE]), quat, 0.3)

    # The hand as it really turned: closing line between the pads, the miss across it (horizontal).
    close_axis = data.geom_xpos[pads[0]] - data.geom_xpos[pads[1]]
    close_axis[2] = 0.0
    close_axis /= np.linalg.norm(close_axis)
    across = np.cross([0.0, 0.0, 1.0], close_axis)
    pad_half = max(_axis_extent(model, data, g, across) for g in pads)
    cube_half = _axis_extent(model, data, cube_geom, across)
    # Along the closing line the site stays on the cube's centre, as the scripts grasp; only across is missed.
    goal = cube_pos + side * (cube_half + pad_half - overlap * 2.0 * pad_half) * across
    goal[2] = grasp_z
    _go(session, np.array([goal[0], goal[1], grasp_z + ABOVE]), quat, 0.4)
    _go(session, goal, quat, 1.0)
    _go(session, goal, quat, 0.2)

    top = 0.0
    session.step([Command(gripper="close")])
    for _ in range(int(CLOSE_S * CONTROL_HZ)):
        top = max(top, float(np.linalg.norm(data.qvel[dof:dof + 3])))
        session.step()
    top = max(top, float(np.linalg.norm(data.qvel[dof:dof + 3])))
    return top


def robot_speeds(robot: str, seeds: int) -> list[float]:
    """Near-miss speeds (m/s) for seeds 0..seeds-1."""
    return [near_miss_speed(robot, s) for s in range(seeds)]


def measure(quick: bool = False) -> dict[str, float]:
    seeds = QUICK_SEEDS if quick else SEEDS
    results: dict[str, float] = {}
    for robot in ROBOTS:
        speeds = robot_speeds(robot, seeds)
        worst = int(np.argmax(speeds))
        print(f"grasp: {robot}: max {max(speeds):.3f} m/s (seed {worst}), median {np.median(speeds):.3f} over {seeds} near misses",
              file=sys.stderr)
        results[f"grasp_edge_max_speed_{robot}"] = round(max(speeds), 3)
    results["grasp_edge_max_object_speed"] = max(results.values())
    return results
