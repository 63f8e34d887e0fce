"""What the session needs to know about a robot, and where it comes from.

A robot is an MJCF file plus the few facts IK and the session cannot guess:
which site is the end effector, which joints the arm drives, the home pose and
how to open and close the gripper. Built-in robots carry these facts here;
users bring their own in a small TOML file (see `load_robot_toml`).
"""

from __future__ import annotations

import tomllib
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

from scenes.errors import TeleopError

ROBOTS_DIR = Path(__file__).parent.parent / "robots"


class SceneError(TeleopError, ValueError):
    """A robot or scene cannot be built; the message is one line naming the problem."""


@dataclass(frozen=True)
class GripperSpec:
    """A gripper driven by one actuator: ctrl `open` opens it, `closed` closes it."""

    actuator: str
    open: float
    closed: float


@dataclass(frozen=True)
class ArmSpec:
    """One arm: the joints IK drives, its end-effector site and its home pose."""

    ee_site: str
    joints: tuple[str, ...]
    home: tuple[float, ...]
    gripper: GripperSpec | None = None
    orientation_cost: float = 1.0
    # Bodies of the hand/gripper that IK keeps off the table (collision avoidance).
    hand_bodies: tuple[str, ...] = ()

    def prefixed(self, prefix: str) -> ArmSpec:
        """The same arm after its model was attached under a name prefix."""
        gripper = None
        if self.gripper is not None:
            gripper = replace(self.gripper, actuator=prefix + self.gripper.actuator)
        return replace(
            self,
            ee_site=prefix + self.ee_site,
            joints=tuple(prefix + j for j in self.joints),
            gripper=gripper,
            hand_bodies=tuple(prefix + b for b in self.hand_bodies),
        )


@dataclass(frozen=True)
class Mount:
    """Where one copy of the robot's MJCF is attached in the arena."""

    prefix: str = ""
    pos: tuple[float, float, float] = (0.0, 0.0, 0.0)
    yaw: float = 0.0  # radians about world z


@dataclass(frozen=True)
class RobotSpec:
    """A robot as the session sees it: MJCF, arms (already prefixed) and mounts.

    `reach` (m) scales task layouts so that objects land where the arm can get
    them; `object_size` is the half-size of the cubes tasks give this robot.
    """

    name: str
    mjcf: Path
    arms: tuple[ArmSpec, ...]
    mounts: tuple[Mount, ...] = (Mount(),)
    reach: float = 0.8
    object_size: float = 0.02
    # Joint names whose actuators the loader had to add: (joint, kp).
    added_actuators: tuple[tuple[str, float], ...] = ()
    builtin: bool = True
    extra: dict = field(default_factory=dict, compare=False)

    @property
    def bimanual(self) -> bool:
        return len(self.arms) > 1

    def to_dict(self) -> dict:
        """JSON-able description, stored in every recording."""
        data = asdict(self)
        data["mjcf"] = str(self.mjcf)
        return data


# --- built-ins -----------------------------------------------------------------

PANDA_HOME = (0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785)


def _panda() -> RobotSpec:
    arm = ArmSpec(
        ee_site="ee_site",
        joints=tuple(f"joint{i}" for i in range(1, 8)),
        home=PANDA_HOME,
        gripper=GripperSpec("gripper", open=0.04, closed=0.0),
        hand_bodies=("hand", "left_finger", "right_finger"),
    )
    return RobotSpec(name="panda", mjcf=ROBOTS_DIR / "panda.xml", arms=(arm,), reach=0.85)


def _ur5e() -> RobotSpec:
    arm = ArmSpec(
        ee_site="ee_site",
        joints=("shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint", "wrist_1_joint", "wrist_2_joint", "wrist_3_joint"),
        home=(-0.3007, -1.717, 1.6873, -1.5411, -1.5708, 1.2701),
        gripper=GripperSpec("gripper", open=0.0425, closed=0.0),
        hand_bodies=("gripper_base", "left_finger", "right_finger"),
    )
    return RobotSpec(name="ur5e", mjcf=ROBOTS_DIR / "ur5e.xml", arms=(arm,), reach=0.9)


def _so101() -> RobotSpec:
    arm = ArmSpec(
        ee_site="ee_site",
        joints=("shoulder_pan", "shoulder_lift", "elbow_flex", "wrist_flex", "wrist_roll"),
        home=(0.0, 0.1511, -0.0935, 1.5132, 0.0),
        gripper=GripperSpec("gripper", open=0.55, closed=0.0),
        # Five joints cannot hold a full pose: weigh orientation low.
        orientation_cost=0.05,
        hand_bodies=("gripper", "moving_jaw"),
    )
    return RobotSpec(name="so101", mjcf=ROBOTS_DIR / "so101.xml", arms=(arm,), reach=0.43, object_size=0.015)


def _bimanual() -> RobotSpec:
    arm = ArmSpec(
        ee_site="ee_site",
        joints=("waist", "shoulder", "elbow", "forearm_roll", "wrist_angle", "wrist_rotate"),
        home=(0.0, -0.188, 0.3155, 0.0, 1.4433, 0.0),
        gripper=GripperSpec("gripper", open=0.037, closed=0.0),
        hand_bodies=("gripper_link", "left_finger", "right_finger"),
    )
    half_gap = 0.42
    return RobotSpec(
        name="bimanual", mjcf=ROBOTS_DIR / "bimanual_arm.xml", arms=(arm, arm), reach=0.75,
        mounts=(Mount("left/", (-half_gap, 0.0, 0.0), 0.0), Mount("right/", (half_gap, 0.0, 0.0), 3.141592653589793)),
    )


BUILTIN_ROBOTS: dict[str, tuple[str, callable]] = {
    "panda": ("Franka Panda, 7-DoF arm with a parallel gripper (default)", _panda),
    "ur5e": ("Universal Robots UR5e, 6-DoF arm with a parallel gripper", _ur5e),
    "so101": ("LeRobot SO-101, 5-DoF arm with a jaw gripper (orientation weighted low)", _so101),
    "bimanual": ("two 6-DoF arms (ViperX-like) facing across one table, ALOHA-style", _bimanual),
}


def register_builtin(name: str, summary: str, factory) -> None:
    """Add a built-in robot (used by scenes/robots_builtin.py)."""
    BUILTIN_ROBOTS[name] = (summary, factory)


def load_robot(name_or_path: str | Path) -> RobotSpec:
    """A built-in robot by name, or a user's robot from a TOML file."""
    key = str(name_or_path)
    if key in BUILTIN_ROBOTS:
        return BUILTIN_ROBOTS[key][1]()
    if key.endswith(".toml") or Path(key).exists():
        return load_robot_toml(Path(key))
    known = ", ".join(sorted(BUILTIN_ROBOTS))
    raise SceneError(f"unknown robot {key!r} (built-ins: {known}; or give a robot .toml file)")


# --- bring your own robot -------------------------------------------------------

_REQUIRED = {"name": str, "mjcf": str, "ee_site": str, "joints": list}


def load_robot_toml(path: Path) -> RobotSpec:
    """Read a user's robot description; raises SceneError naming the first problem.

    Checking the names against the compiled model happens in `scenes.assembly.build`,
    where the model exists; here the file's own shape is checked.
    """
    if not path.is_file():
        raise SceneError(f"{path}: no such robot file")
    try:
        raw = tomllib.loads(path.read_text())
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise SceneError(f"{path}: not valid TOML ({exc})") from None
    for key, kind in _REQUIRED.items():
        if key not in raw:
            raise SceneError(f"{path}: missing required field '{key}'")
        if not isinstance(raw[key], kind):
            raise SceneError(f"{path}: field '{key}' must be a {kind.__name__}")
    joints = raw["joints"]
    if not joints or not all(isinstance(j, str) for j in joints):
        raise SceneError(f"{path}: field 'joints' must be a non-empty list of joint names")
    mjcf = Path(raw["mjcf"])
    if not mjcf.is_absolute():
        mjcf = path.parent / mjcf
    if not mjcf.is_file():
        raise SceneError(f"{path}: mjcf file {mjcf} not found")

    home = raw.get("home", "home")
    if isinstance(home, list):
        if len(home) != len(joints) or not all(isinstance(v, (int, float)) for v in home):
            raise SceneError(f"{path}: field 'home' must list {len(joints)} numbers (one per joint) or name a keyframe")
        home_values: tuple[float, ...] = tuple(float(v) for v in home)
        extra = {}
    elif isinstance(home, str):
        home_values = ()
        extra = {"home_key": home}
    else:
        raise SceneError(f"{path}: field 'home' must be a list of numbers or a keyframe name")

    orientation_cost = raw.get("orientation_cost", 1.0)
    if not isinstance(orientation_cost, (int, float)) or orientation_cost < 0:
        raise SceneError(f"{path}: field 'orientation_cost' must be a number >= 0")

    gripper = None
    if "gripper" in raw:
        g = raw["gripper"]
        if not isinstance(g, dict):
            raise SceneError(f"{path}: [gripper] must be a table")
        for key in ("actuator", "open", "closed"):
            if key not in g:
                raise SceneError(f"{path}: [gripper] is missing '{key}'")
        if not isinstance(g["actuator"], str):
            raise SceneError(f"{path}: [gripper] 'actuator' must be an actuator name")
        if not all(isinstance(g[k], (int, float)) for k in ("open", "closed")):
            raise SceneError(f"{path}: [gripper] 'open' and 'closed' must be numbers")
        gripper = GripperSpec(g["actuator"], float(g["open"]), float(g["closed"]))

    kp = raw.get("kp", 300.0)
    if not isinstance(kp, (int, float)) or kp <= 0:
        raise SceneError(f"{path}: field 'kp' must be a positive number")
    extra["kp"] = float(kp)
    if "forcerange" in raw:
        extra["forcerange"] = float(raw["forcerange"])
    extra["toml"] = str(path)

    arm = ArmSpec(
        ee_site=raw["ee_site"],
        joints=tuple(joints),
        home=home_values,
        gripper=gripper,
        orientation_cost=float(orientation_cost),
    )
    return RobotSpec(name=raw["name"], mjcf=mjcf, arms=(arm,), reach=float(raw.get("reach", 0.0)), builtin=False, extra=extra)
