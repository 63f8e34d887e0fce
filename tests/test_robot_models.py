"""The hand-written robot models (ur5e, so101, bimanual_arm) behave like robots.

Every check runs real MuJoCo physics on the MJCF file alone (no arena): 2 ms steps with
the implicitfast integrator, gravity on, the arm held by its own position actuators.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np
import pytest

ROBOTS_DIR = Path(__file__).resolve().parents[1] / "scenes" / "robots"
DT = 0.002


@dataclass(frozen=True)
class Robot:
    file: str
    joints: tuple[str, ...]  # arm joints, in actuator order
    gripper: str  # gripper actuator
    open: float  # gripper ctrl when open
    closed: float  # gripper ctrl when closed
    pads: tuple[str, str]  # fingertip pad geoms
    box_half: float  # half size of the cube the gripper must hold
    box_mass: float
    symmetric: bool = True  # parallel gripper (pad midpoint fixed) or one moving jaw


ROBOTS = {
    "ur5e": Robot(
        "ur5e.xml",
        ("shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint", "wrist_1_joint", "wrist_2_joint", "wrist_3_joint"),
        "gripper", 0.0425, 0.0, ("left_pad", "right_pad"), 0.02, 0.1,
    ),
    "so101": Robot(
        "so101.xml",
        ("shoulder_pan", "shoulder_lift", "elbow_flex", "wrist_flex", "wrist_roll"),
        "gripper", 0.55, 0.0, ("fixed_pad", "moving_pad"), 0.0125, 0.03, symmetric=False,
    ),
    "bimanual_arm": Robot(
        "bimanual_arm.xml",
        ("waist", "shoulder", "elbow", "forearm_roll", "wrist_angle", "wrist_rotate"),
        "gripper", 0.037, 0.0, ("left_pad", "right_pad"), 0.02, 0.1,
    ),
}

params = pytest.mark.parametrize("name", list(ROBOTS))


def load(name: str) -> tuple[mujoco.MjModel, mujoco.MjData]:
    model = mujoco.MjModel.from_xml_path(str(ROBOTS_DIR / ROBOTS[name].file))
    model.opt.timestep = DT
    model.opt.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    data = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, data, model.key("home").id)
    mujoco.mj_forward(model, data)
    return model, data


def joint_actuator(model: mujoco.MjModel, joint: str) -> int:
    """The one actuator that drives `joint` directly."""
    jid = model.joint(joint).id
    acts = [a for a in range(model.nu) if model.actuator_trntype[a] == mujoco.mjtTrn.mjTRN_JOINT
            and model.actuator_trnid[a, 0] == jid]
    assert len(acts) == 1, joint
    return acts[0]


def arm_qpos_ids(model: mujoco.MjModel, robot: Robot) -> np.ndarray:
    return np.array([model.jnt_qposadr[model.joint(j).id] for j in robot.joints])


def run(model: mujoco.MjModel, data: mujoco.MjData, seconds: float) -> None:
    for _ in range(round(seconds / DT)):
        mujoco.mj_step(model, data)


def pad_midpoint(model: mujoco.MjModel, data: mujoco.MjData, robot: Robot) -> np.ndarray:
    a, b = (data.geom(p).xpos for p in robot.pads)
    return (a + b) / 2


def set_gripper(model: mujoco.MjModel, data: mujoco.MjData, robot: Robot, value: float) -> None:
    data.ctrl[model.actuator(robot.gripper).id] = value


@params
def test_model_structure(name: str) -> None:
    robot = ROBOTS[name]
    model, data = load(name)
    # The base is the first body in worldbody, at the origin, unrotated.
    assert model.body_parentid[1] == 0
    assert np.allclose(model.body_pos[1], 0) and np.allclose(model.body_quat[1], [1, 0, 0, 0])
    assert model.body_jntnum[1] == 0, "the base must not move"
    # Every moving body is gravity compensated.
    for b in range(2, model.nbody):
        assert model.body_gravcomp[b] == 1, model.body(b).name
    # One position actuator per arm joint, ctrlrange = joint range, realistic force limit.
    for j in robot.joints:
        jid = model.joint(j).id
        a = joint_actuator(model, j)
        assert model.actuator_gaintype[a] == mujoco.mjtGain.mjGAIN_FIXED and model.actuator_biasprm[a, 1] < 0
        assert model.jnt_limited[jid] and np.allclose(model.actuator_ctrlrange[a], model.jnt_range[jid])
        assert model.actuator_forcelimited[a] and 0 < model.actuator_forcerange[a, 1] <= 150
        assert model.dof_armature[model.jnt_dofadr[jid]] > 0 and model.dof_damping[model.jnt_dofadr[jid]] > 0
    assert model.nu == len(robot.joints) + 1, "arm actuators plus one gripper actuator"
    lo, hi = model.actuator_ctrlrange[model.actuator(robot.gripper).id]
    assert lo <= min(robot.open, robot.closed) and max(robot.open, robot.closed) <= hi
    # Home: gripper open, ctrl equal to the arm's home pose.
    home = model.key("home")
    ids = arm_qpos_ids(model, robot)
    for i, j in enumerate(robot.joints):
        assert home.ctrl[joint_actuator(model, j)] == pytest.approx(home.qpos[ids[i]])
    assert home.ctrl[model.actuator(robot.gripper).id] == pytest.approx(robot.open)
    # Friction pads on the fingertips, ee site and wrist camera present.
    for p in robot.pads:
        g = model.geom(p)
        assert g.condim[0] == 4 and g.priority[0] >= 1 and g.friction[0] >= 1.0
    model.site("ee_site")
    model.camera("wrist")
    # Links carry the published masses: the arm weighs what the real one does (within reason).
    lo_mass, hi_mass = {"ur5e": (20, 25), "so101": (0.5, 1.0), "bimanual_arm": (3.5, 5.5)}[name]
    assert lo_mass < model.body_subtreemass[1] < hi_mass


@params
def test_home_has_no_self_contact_and_is_above_workspace(name: str) -> None:
    model, data = load(name)
    assert data.ncon == 0, [
        (model.body(model.geom_bodyid[c.geom1]).name, model.body(model.geom_bodyid[c.geom2]).name)
        for c in data.contact[: data.ncon]
    ]
    ee = data.site("ee_site")
    assert ee.xpos[0] > 0.1, "home reaches forward, along +x"
    assert ee.xpos[2] > 0.05, "home is above the base"
    # Hand points down at home.
    assert ee.xmat.reshape(3, 3)[2, 2] < -0.95


@params
def test_home_holds_still(name: str) -> None:
    model, data = load(name)
    home = model.key("home").qpos.copy()
    run(model, data, 2.0)
    assert np.max(np.abs(data.qpos - home)) < 1e-3


@params
def test_position_actuators_track_a_step(name: str) -> None:
    robot = ROBOTS[name]
    model, data = load(name)
    ids = arm_qpos_ids(model, robot)
    for i, j in enumerate(robot.joints):
        mujoco.mj_resetDataKeyframe(model, data, model.key("home").id)
        lo, hi = model.joint(j).range
        target = data.qpos[ids[i]] + (0.3 if data.qpos[ids[i]] + 0.3 <= hi else -0.3)
        data.ctrl[joint_actuator(model, j)] = target
        run(model, data, 0.5)
        assert abs(data.qpos[ids[i]] - target) < 0.01, (j, data.qpos[ids[i]], target)
    # All joints at once.
    mujoco.mj_resetDataKeyframe(model, data, model.key("home").id)
    targets = data.qpos[ids] + 0.3
    for i, j in enumerate(robot.joints):
        lo, hi = model.joint(j).range
        if targets[i] > hi:
            targets[i] -= 0.6
    data.ctrl[[joint_actuator(model, j) for j in robot.joints]] = targets
    run(model, data, 0.5)
    assert np.max(np.abs(data.qpos[ids] - targets)) < 0.01


@params
def test_gripper_closes_quickly(name: str) -> None:
    robot = ROBOTS[name]
    model, data = load(name)
    act = model.actuator(robot.gripper).id
    assert data.actuator_length[act] == pytest.approx(robot.open, abs=1e-3)
    set_gripper(model, data, robot, robot.closed)
    t_closed = None
    for step in range(round(0.5 / DT)):
        mujoco.mj_step(model, data)
        if abs(data.actuator_length[act] - robot.closed) < 0.05 * abs(robot.open - robot.closed):
            t_closed = (step + 1) * DT
            break
    assert t_closed is not None and t_closed < 0.5
    run(model, data, 0.5)
    set_gripper(model, data, robot, robot.open)
    run(model, data, 0.5)
    assert data.actuator_length[act] == pytest.approx(robot.open, abs=0.05 * abs(robot.open - robot.closed))


def with_box(name: str) -> tuple[mujoco.MjModel, mujoco.MjData, int]:
    """The robot at home, gripper open, a free cube centred on (and aligned with) ee_site."""
    robot = ROBOTS[name]
    model, data = load(name)
    ee = data.site("ee_site")
    quat = np.zeros(4)
    mujoco.mju_mat2Quat(quat, ee.xmat)
    spec = mujoco.MjSpec.from_file(str(ROBOTS_DIR / robot.file))
    home = model.key("home")
    spec.delete(spec.key("home"))
    box = spec.worldbody.add_body(name="box")
    box.add_freejoint()
    box.add_geom(type=mujoco.mjtGeom.mjGEOM_BOX, size=[robot.box_half] * 3, mass=robot.box_mass,
                 rgba=[0.8, 0.2, 0.2, 1])
    bmodel = spec.compile()
    bmodel.opt.timestep = DT
    bmodel.opt.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    bdata = mujoco.MjData(bmodel)
    bdata.qpos[: model.nq] = home.qpos
    bdata.qpos[model.nq: model.nq + 3] = ee.xpos
    bdata.qpos[model.nq + 3: model.nq + 7] = quat
    bdata.ctrl[:] = home.ctrl
    mujoco.mj_forward(bmodel, bdata)
    return bmodel, bdata, bmodel.body("box").id


@params
@pytest.mark.parametrize("physics", ["default", "arena"])
def test_grasp_holds_a_cube_at_the_ee_site(name: str, physics: str) -> None:
    """Close on a free cube that starts at the ee site (gravity on from the start)."""
    robot = ROBOTS[name]
    model, data, box = with_box(name)
    if physics == "arena":  # the options scenes/assembly/arena.py sets
        model.opt.cone = mujoco.mjtCone.mjCONE_ELLIPTIC
        model.opt.impratio = 10.0
    assert data.ncon == 0, "the cube starts clear of the open gripper"
    set_gripper(model, data, robot, robot.closed)
    run(model, data, 0.5)
    dists = []
    for _ in range(round(2.0 / DT)):
        mujoco.mj_step(model, data)
        dists.append(np.linalg.norm(data.xpos[box] - data.site("ee_site").xpos))
    assert max(dists) < 0.01, max(dists)
    # Held by the two pads and nothing else.
    touching = set()
    for c in data.contact[: data.ncon]:
        if box in (model.geom_bodyid[c.geom1], model.geom_bodyid[c.geom2]):
            other = c.geom2 if model.geom_bodyid[c.geom1] == box else c.geom1
            touching.add(model.geom(other).name)
    assert touching == set(robot.pads)
    # The arm itself stayed at home while holding it.
    home = load(name)[0].key("home").qpos
    ids = arm_qpos_ids(model, robot)
    assert np.max(np.abs(data.qpos[ids] - home[ids])) < 0.02


@params
def test_ee_site_sits_between_the_pads(name: str) -> None:
    robot = ROBOTS[name]
    model, data = load(name)
    ee = data.site("ee_site").xpos.copy()
    a, b = (data.geom(p).xpos.copy() for p in robot.pads)
    # Open: the site is between the pads and at their midpoint.
    assert np.linalg.norm((a + b) / 2 - ee) < 0.005
    axis = (b - a) / np.linalg.norm(b - a)
    assert 0 < np.dot(ee - a, axis) < np.linalg.norm(b - a)
    if robot.symmetric:
        # Closed (parallel fingers): the midpoint does not move.
        set_gripper(model, data, robot, robot.closed)
        run(model, data, 0.5)
        assert np.linalg.norm(pad_midpoint(model, data, robot) - data.site("ee_site").xpos) < 0.005
    # Closed on the cube: the pads' midpoint (the grasped cube's centre) is at the site.
    model, data, box = with_box(name)
    set_gripper(model, data, robot, robot.closed)
    run(model, data, 0.5)
    mid = pad_midpoint(model, data, robot)
    assert np.linalg.norm(mid - data.site("ee_site").xpos) < 0.005
    assert np.linalg.norm(mid - data.xpos[box]) < 0.005


def test_two_bimanual_arms_attach_facing_each_other() -> None:
    """The lead attaches two copies (prefixes left/ and right/) across a table."""
    parent = mujoco.MjSpec()
    for prefix, x, yaw in (("left/", -0.45, 0.0), ("right/", 0.45, np.pi)):
        child = mujoco.MjSpec.from_file(str(ROBOTS_DIR / "bimanual_arm.xml"))
        frame = parent.worldbody.add_frame(pos=[x, 0, 0], quat=[np.cos(yaw / 2), 0, 0, np.sin(yaw / 2)])
        parent.attach(child, prefix=prefix, frame=frame)
    model = parent.compile()
    model.opt.timestep = DT
    model.opt.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    data = mujoco.MjData(model)
    single = mujoco.MjModel.from_xml_path(str(ROBOTS_DIR / "bimanual_arm.xml"))
    home = single.key("home")
    n, nu = single.nq, single.nu
    data.qpos[:] = np.concatenate([home.qpos, home.qpos])
    data.ctrl[:] = np.concatenate([home.ctrl, home.ctrl])
    mujoco.mj_forward(model, data)
    assert data.ncon == 0
    left, right = data.site("left/ee_site").xpos.copy(), data.site("right/ee_site").xpos.copy()
    assert left[0] < 0 < right[0] and abs(left[1]) < 1e-6 and abs(right[1]) < 1e-6
    # Each arm is driven independently: move only the left waist.
    data.ctrl[model.actuator("left/waist").id] = 0.3
    run(model, data, 0.5)
    assert abs(data.qpos[model.joint("left/waist").qposadr[0]] - 0.3) < 0.01
    assert np.max(np.abs(data.qpos[n:] - home.qpos)) < 1e-3
    assert model.camera("left/wrist") and model.camera("right/wrist")
    assert nu == 7


@params
def test_ee_follows_a_moving_target(name: str) -> None:
    """Servos stiff enough for teleop: the EE lags a 0.25 m/s target by under 5 mm."""
    robot = ROBOTS[name]
    model, data = load(name)
    target = mujoco.MjData(model)  # kinematic copy: where the commanded joints put the EE
    target.qpos[:] = data.qpos
    ids = arm_qpos_ids(model, robot)
    dofs = [model.jnt_dofadr[model.joint(j).id] for j in robot.joints]
    acts = [joint_actuator(model, j) for j in robot.joints]
    site = model.site("ee_site").id
    for direction in ([1.0, 0, 0], [0, 1.0, 0], [0, 0, -1.0]):
        mujoco.mj_resetDataKeyframe(model, data, model.key("home").id)
        target.qpos[:] = data.qpos
        step = 0.25 * DT * np.array(direction)
        lags = []
        for _ in range(round(0.4 / DT)):
            mujoco.mj_kinematics(model, target)
            mujoco.mj_comPos(model, target)
            jac = np.zeros((3, model.nv))
            mujoco.mj_jacSite(model, target, jac, None, site)
            jac = jac[:, dofs]
            target.qpos[ids] += jac.T @ np.linalg.solve(jac @ jac.T + 1e-8 * np.eye(3), step)
            mujoco.mj_kinematics(model, target)
            data.ctrl[acts] = target.qpos[ids]
            mujoco.mj_step(model, data)
            lags.append(np.linalg.norm(target.site_xpos[site] - data.site_xpos[site]))
        assert max(lags[len(lags) // 2:]) < 0.005, (direction, max(lags))
