"""What the tests share (and the bench, which imports from here, never the other way round).

The real CLI in a fresh process; a script, a robot, a contact-rich scene written
here; a small file system that fills up; a private X display's keys; the
processes a job leaves behind; waiting on something another thread does; a
LeRobot dataset's columns. Fixtures built on these are in tests/conftest.py.
Units: metres, seconds, like everything else.
"""

from __future__ import annotations

import contextlib
import json
import os
import platform
import resource
import signal
import subprocess
import sys
import textwrap
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import TYPE_CHECKING, Any

import mujoco
import numpy as np

from recorder.format import ArmMeta, EpisodeMeta
from tests.warm_cli import WARM, with_project_path

if TYPE_CHECKING:
    import gymnasium

ROOT = Path(__file__).resolve().parent.parent
PICK = ROOT / "scenes" / "scripts" / "lift_pick.json"  # the scripted lift pick, 144 steps at 30 Hz


# -- the command line, in a fresh process ------------------------------------------------------


def run_cli(*args: str, timeout: float = 300, env: dict | None = None, cwd: Path | None = None) -> subprocess.CompletedProcess:
    """`teleop ARGS...` in a fresh process, as a user would run it: forked from this worker's warm process
    (tests/warm_cli.py: the third-party imports already done) unless the environment asks for a real interpreter."""
    return run_teleop(list(args), with_project_path({**os.environ, **(env or {})}), cwd or ROOT, timeout)


def run_teleop(args: list[str], env: dict[str, str], cwd: Path, timeout: float) -> subprocess.CompletedProcess:
    """As run_cli, with exactly the environment `env` (a test that takes variables away, such as DISPLAY)."""
    if WARM.usable_for(env):
        return WARM.run(list(args), env, cwd, timeout)
    return subprocess.run([sys.executable, "-m", "teleop", *args], capture_output=True, text=True, timeout=timeout,
                          env=env, cwd=cwd)


def popen_cli(args: list[str], stdout, env: dict | None = None, cwd: Path | None = None, stderr: int | None = None):
    """`teleop ARGS...` started in a fresh process (as run_cli: forked from the warm process when it may be),
    stdout to the file `stdout` and stderr with it, or to the file descriptor `stderr` (a pipe the test reads):
    a subprocess.Popen, or what the tests use of one (pid, poll, wait, send_signal, terminate, kill, returncode)."""
    full_env = with_project_path({**os.environ, **(env or {})})
    if WARM.usable_for(full_env):
        return WARM.popen(list(args), full_env, cwd or ROOT, stdout.fileno(), stdout.fileno() if stderr is None else stderr)
    return subprocess.Popen([sys.executable, "-m", "teleop", *args], stdout=stdout,
                            stderr=subprocess.STDOUT if stderr is None else stderr, env=full_env, cwd=cwd or ROOT)


def run_script(argv: list[str], env: dict, cwd: Path, timeout: float, ignore=()) -> subprocess.CompletedProcess:
    """A console script (`lerobot-train ARGS`, argv[0] its path) with environment `env` in a fresh process, as
    run_cli: forked from the warm process unless `env` differs where imports look (`ignore`: the test's own
    variables, read by no import, e.g. WANDB_MODE)."""
    # PYTHONPATH: the script's own needs none, and the forked child has the project on its path as the warm
    # process has (no module of LeRobot's is named like one of ours)
    if WARM.usable_for(env, (*ignore, "PYTHONPATH")):
        return WARM.run(argv[1:], env, cwd, timeout, script=argv[0])
    return subprocess.run(argv, capture_output=True, text=True, env=env, cwd=cwd, timeout=timeout)


def run_json(*args: str, **kwargs) -> dict:
    """Run a CLI command that prints one JSON object, and parse it."""
    result = run_cli(*args, **kwargs)
    assert result.returncode == 0, f"exit {result.returncode}: {result.stderr[-2000:]}"
    return json.loads(result.stdout)


def write_script(path: Path, steps: list[dict]) -> Path:
    path.write_text(json.dumps({"steps": steps}))
    return path


def assert_one_line_error(result: subprocess.CompletedProcess, *needles: str) -> None:
    """Exit 2, a single line on stderr naming the problem, no traceback."""
    assert result.returncode == 2, f"exit {result.returncode}: {result.stderr}"
    lines = [line for line in result.stderr.strip().splitlines() if line.strip()]
    assert len(lines) == 1, f"expected one line, got: {result.stderr!r}"
    assert "Traceback" not in result.stderr
    for needle in needles:
        assert needle in lines[0], f"{needle!r} not in {lines[0]!r}"


def run_main(*args: str) -> subprocess.CompletedProcess:
    """`teleop ARGS...` through the CLI's entry point in this process: its exit code and what it wrote to
    sys.stdout and sys.stderr. For flags' and files' errors, where a fresh process only adds ~1-2 s of imports;
    a signal, a kill, or output written to file descriptors 1 and 2 directly still want `run_cli`."""
    import io

    from teleop.cli.entry import main

    out, err = io.StringIO(), io.StringIO()
    sigterm = signal.getsignal(signal.SIGTERM)  # main() makes SIGTERM end a command the way Ctrl-C does
    environ = dict(os.environ)  # and a command may set variables for its own children (export: quiet_environment)
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err), warnings.catch_warnings():
            try:
                code = main(list(args))
            except SystemExit as exc:  # argparse: a usage error (2) or --help (0)
                code = exc.code if isinstance(exc.code, int) else 1
    finally:
        signal.signal(signal.SIGTERM, sigterm)
        os.environ.clear()
        os.environ.update(environ)
    return subprocess.CompletedProcess(["teleop", *args], code, out.getvalue(), err.getvalue())


def record_script(directory: Path, script: Path, *flags: str, **kwargs) -> dict:
    """`teleop run --device script:SCRIPT --record DIRECTORY FLAGS... --json` in a fresh process; its summary."""
    return run_json("run", "--device", f"script:{script}", "--record", str(directory), *flags, "--json", **kwargs)


# -- waiting on another thread or process -------------------------------------------------------


def wait_until(condition: Callable[[], Any], timeout_s: float = 5.0, what: str | None = None) -> Any:
    """Poll `condition` until it is truthy or `timeout_s` passes; its last value. With `what`,
    a timeout fails the test naming what did not happen."""
    deadline = time.monotonic() + timeout_s
    while True:
        value = condition()
        if value or time.monotonic() >= deadline:
            break
        time.sleep(0.02)
    assert value or what is None, f"timed out waiting for {what}"
    return value


def children_of(pid: int) -> dict[int, str]:
    """{pid: start time} of the processes whose parent is `pid` (start time: against pid reuse)."""
    found = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
            except OSError:
                continue
            if int(fields[1]) == pid:
                found[int(entry.name)] = fields[19]
    return found


def descendants_of(pid: int) -> dict[int, str]:
    """{pid: start time} of the processes under `pid`: its children, theirs, and so on (a job's local workers
    are the children of multiprocessing's fork server, itself a child of the job)."""
    found: dict[int, str] = {}
    todo = [pid]
    while todo:
        for child, started in children_of(todo.pop()).items():
            if child not in found:
                found[child] = started
                todo.append(child)
    return found


def alive(pid: int, started: str) -> bool:
    """Still running: the same process (same start time) and not a zombie waiting to be reaped."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return False
    return fields[19] == started and fields[0] != "Z"


# -- a private X display (the keyboard tests' Xvfb; the fixture is in conftest.py) ---------------


def xdotool(display: str, *args: str) -> float:
    """Send keys to the display; returns the time (monotonic) when xdotool finished."""
    subprocess.run(["xdotool", *args], env={**os.environ, "DISPLAY": display}, check=True, timeout=10)
    return time.monotonic()


# -- a disk that fills up ---------------------------------------------------------------------


CAUSES = ("No space left on device", "File too large")  # what a full disk's one-line errors name


@dataclass
class SmallFs:
    """A directory where writing fails early: a small tmpfs, or a per-file size limit to apply."""

    path: Path
    file_limit: int | None  # bytes (RLIMIT_FSIZE) when not a tmpfs

    def preexec(self):
        """For subprocess: the child gets the file size limit, and EFBIG instead of SIGXFSZ."""
        if self.file_limit is None:
            return None
        limit = self.file_limit

        def apply() -> None:
            signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
            resource.setrlimit(resource.RLIMIT_FSIZE, (limit, resource.getrlimit(resource.RLIMIT_FSIZE)[1]))

        return apply

    @contextlib.contextmanager
    def limited(self):
        """In this process: the file size limit while the block runs (a tmpfs needs none)."""
        if self.file_limit is None:
            yield
            return
        old_limit = resource.getrlimit(resource.RLIMIT_FSIZE)
        old_handler = signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (self.file_limit, old_limit[1]))
        try:
            yield
        finally:
            resource.setrlimit(resource.RLIMIT_FSIZE, old_limit)
            signal.signal(signal.SIGXFSZ, old_handler)

    @contextlib.contextmanager
    def full(self, growing: Path):
        """In this process, while the block runs: no room for `growing` (a file being written) to grow. On a tmpfs a
        filler file takes the free space (removed after); otherwise the file size limit is `growing`'s size now.
        For a test whose premise is what was written first (a flush seen on disk) and only then a full disk."""
        if self.file_limit is not None:
            with SmallFs(self.path, growing.stat().st_size).limited():
                yield
            return
        filler = self.path / "filler.bin"
        with open(filler, "wb", buffering=0) as f:
            try:
                while True:
                    f.write(bytes(4096))
            except OSError:  # ENOSPC: full
                pass
        try:
            yield
        finally:
            filler.unlink()


@contextlib.contextmanager
def small_fs(tmp_path: Path, tmpfs_kb: int, file_limit: int):
    """A tmpfs of `tmpfs_kb` KiB as root (unmounted afterwards, always), else RLIMIT_FSIZE of `file_limit` bytes."""
    path = tmp_path / "small"
    path.mkdir()
    mounted = False
    if os.geteuid() == 0 and os.environ.get("TELEOP_TEST_SMALL_FS") != "rlimit":  # rlimit: test the fallback as root
        done = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={tmpfs_kb}k", "tmpfs", str(path)],
                              capture_output=True, text=True)
        mounted = done.returncode == 0  # a container without the right to mount: fall back to the limit
    try:
        yield SmallFs(path, None if mounted else file_limit)
    finally:
        if mounted:
            subprocess.run(["umount", "-l", str(path)], check=False)


# -- a robot of the user's own: TOML + MJCF with a mesh and motor actuators -----------------------


# A 6-DoF arm unlike the built-ins: an elbow-up anthropomorphic arm driven by
# motors (the loader must replace them with position actuators), a mesh base
# loaded from the model's own folder, and a two-finger gripper.
ARM_XML = """
<mujoco model="test_arm">
  <compiler angle="radian" meshdir="meshes"/>
  <asset><mesh name="base_mesh" file="base.obj"/></asset>
  <worldbody>
    <body name="base">
      <geom type="mesh" mesh="base_mesh" rgba="0.3 0.3 0.35 1"/>
      <body name="l1" pos="0 0 0.12">
        <joint name="j1" axis="0 0 1" range="-3 3" armature="0.05" damping="1"/>
        <geom type="cylinder" pos="0 0 0.03" size="0.05 0.025" mass="2"/>
        <body name="l2" pos="0 0 0.06">
          <joint name="j2" axis="0 1 0" range="-2 2" armature="0.05" damping="1"/>
          <geom type="capsule" fromto="0 0 0 0 0 0.3" size="0.04" mass="2"/>
          <body name="l3" pos="0 0 0.3">
            <joint name="j3" axis="0 1 0" range="-2.5 2.5" armature="0.05" damping="1"/>
            <geom type="capsule" fromto="0 0 0 0.28 0 0" size="0.035" mass="1.2"/>
            <body name="l4" pos="0.28 0 0">
              <joint name="j4" axis="1 0 0" range="-3 3" armature="0.02" damping="0.5"/>
              <geom type="capsule" fromto="0 0 0 0.05 0 0" size="0.03" mass="0.4"/>
              <body name="l5" pos="0.05 0 0">
                <joint name="j5" axis="0 1 0" range="-2 2" armature="0.02" damping="0.5"/>
                <geom type="capsule" fromto="0 0 0 0.05 0 0" size="0.03" mass="0.3"/>
                <body name="l6" pos="0.05 0 0">
                  <joint name="j6" axis="1 0 0" range="-3 3" armature="0.02" damping="0.5"/>
                  <geom type="box" pos="0.015 0 0" size="0.015 0.05 0.02" mass="0.3"/>
                  <site name="tool_center" pos="0.075 0 0" size="0.005"/>
                  <body name="fa" pos="0.03 0 0">
                    <joint name="fa" type="slide" axis="0 1 0" range="0 0.035" damping="2"/>
                    <geom type="box" pos="0.045 0.006 0" size="0.035 0.005 0.01" mass="0.02" friction="1.5" condim="4"/>
                  </body>
                  <body name="fb" pos="0.03 0 0">
                    <joint name="fb" type="slide" axis="0 -1 0" range="0 0.035" damping="2"/>
                    <geom type="box" pos="0.045 -0.006 0" size="0.035 0.005 0.01" mass="0.02" friction="1.5" condim="4"/>
                  </body>
                </body>
              </body>
            </body>
          </body>
        </body>
      </body>
    </body>
  </worldbody>
  <tendon><fixed name="grip"><joint joint="fa" coef="0.5"/><joint joint="fb" coef="0.5"/></fixed></tendon>
  <equality><joint joint1="fa" joint2="fb"/></equality>
  <actuator>
    <motor name="m1" joint="j1" gear="1"/>
    <motor name="m2" joint="j2" gear="1"/>
    <position name="fingers" tendon="grip" kp="300" ctrlrange="0 0.035"/>
  </actuator>
  <keyframe><key name="ready" qpos="0 0 0.3 0 1.27 0 0.035 0.035"/></keyframe>
</mujoco>
"""

CUBE_OBJ = "\n".join(
    [f"v {x} {y} {z}" for x in (-0.07, 0.07) for y in (-0.07, 0.07) for z in (0.0, 0.12)]
    + ["f 1 2 4 3", "f 5 7 8 6", "f 1 5 6 2", "f 3 4 8 7", "f 1 3 7 5", "f 2 6 8 4"]
)


def make_robot(folder: Path, toml_body: str | None = None) -> Path:
    (folder / "meshes").mkdir(parents=True, exist_ok=True)
    (folder / "meshes" / "base.obj").write_text(CUBE_OBJ)
    (folder / "test_arm.xml").write_text(ARM_XML)
    toml = folder / "test_arm.toml"
    toml.write_text(toml_body if toml_body is not None else textwrap.dedent("""
        name = "test_arm"
        mjcf = "test_arm.xml"
        ee_site = "tool_center"
        joints = ["j1", "j2", "j3", "j4", "j5", "j6"]
        home = "ready"
        orientation_cost = 0.5
        kp = 2500
        [gripper]
        actuator = "fingers"
        open = 0.035
        closed = 0.0
    """))
    return toml

# -- the pusher: a slider and a pile of free boxes, recorded without a robot ---------------------
# Contacts appear, move and vanish, so an inexact replay shows at once (the recorder's and replay's tests).

SUBSTEPS = 25
TIMESTEP = 0.002  # s


def pusher_xml(n_boxes: int = 9) -> str:
    """A position-driven slider ("the arm") and a pile of free boxes on a plane."""
    boxes = []
    for i in range(n_boxes):
        x = 0.25 + 0.09 * (i % 3)
        y = -0.09 + 0.09 * ((i // 3) % 3)
        z = 0.04 + 0.085 * (i // 9) + 0.002 * i
        boxes.append(
            f'<body name="box{i}" pos="{x:.3f} {y:.3f} {z:.3f}"><freejoint/>'
            f'<geom type="box" size=".04 .04 .04" mass="0.2" rgba=".8 .4 .2 1"/></body>'
        )
    return f"""<mujoco model="pusher">
  <compiler angle="radian"/>
  <option timestep="{TIMESTEP}"/>
  <worldbody>
    <light pos="0 0 3"/>
    <geom name="floor" type="plane" size="2 2 0.1" friction="0.9"/>
    <body name="pusher" pos="0 0 0.05">
      <joint name="px" type="slide" axis="1 0 0" range="-0.5 1.2" limited="true" damping="5"/>
      <joint name="py" type="slide" axis="0 1 0" range="-0.6 0.6" limited="true" damping="5"/>
      <geom type="box" size="0.04 0.16 0.04" mass="3"/>
      <site name="ee" pos="0 0 0.05" euler="0 0 0.7"/>
    </body>
    {''.join(boxes)}
  </worldbody>
  <actuator>
    <position name="ax" joint="px" kp="600" dampratio="1" ctrlrange="-0.5 1.2"/>
    <position name="ay" joint="py" kp="600" dampratio="1" ctrlrange="-0.6 0.6"/>
  </actuator>
</mujoco>"""


def episode_meta(model: mujoco.MjModel, xml: str, index: int, seed: int, substeps: int, *,
                 scene: str = "pusher", arms: tuple[ArmMeta, ...] | None = None,
                 assets: dict | None = None) -> EpisodeMeta:
    """Metadata the way the session fills it, for a model built here."""
    arms = arms or (ArmMeta(ee_site="ee", joints=("px", "py"), actuators=("ax", "ay"), home=(0.0, 0.0)),)
    return EpisodeMeta(
        scene=scene,
        robot="pusher",
        arms=arms,
        nstate=mujoco.mj_stateSize(model, mujoco.mjtState.mjSTATE_INTEGRATION),
        nq=model.nq,
        nv=model.nv,
        nu=model.nu,
        control_hz=1.0 / (model.opt.timestep * substeps),
        timestep=model.opt.timestep,
        substeps=substeps,
        seed=seed,
        task="push the boxes",
        model_xml=xml,
        assets=assets or {},
        mujoco_version=mujoco.__version__,
        platform=platform.platform(),
        machine=platform.machine(),
        python_version=sys.version.split()[0],
        start_time=datetime.now(timezone.utc).isoformat(),
        episode_index=index,
        source="script",
    )


def pusher_ctrl(k: int, seed: int, dt: float) -> np.ndarray:
    """Scripted slider targets: sweep through the pile and back, with a seeded wobble."""
    t = k * dt
    phase = 0.3 * seed
    return np.array([0.45 - 0.55 * np.cos(0.9 * t + phase), 0.25 * np.sin(1.7 * t + phase)])


def record_pusher_episode(
    directory: Path,
    index: int = 0,
    steps: int = 200,
    formats: tuple[str, ...] = ("mcap", "hdf5"),
    seed: int = 0,
    substeps: int = SUBSTEPS,
    on_step: Callable[[int, mujoco.MjData], None] | None = None,
    success: bool = True,
    complete: bool = True,
) -> list[Path]:
    """Run the pusher scene like the session does and record it; returns the files."""
    from recorder import EpisodeWriter, StepRecord

    xml = pusher_xml()
    model = mujoco.MjModel.from_xml_string(xml)
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    site = model.site("ee").id
    nstate = mujoco.mj_stateSize(model, mujoco.mjtState.mjSTATE_INTEGRATION)
    writer = EpisodeWriter(directory, index, formats, episode_meta(model, xml, index, seed, substeps))
    dt = model.opt.timestep * substeps
    quat = np.empty(4)
    for k in range(steps):
        state = np.empty(nstate)
        mujoco.mj_getState(model, data, state, mujoco.mjtState.mjSTATE_INTEGRATION)
        t, qpos, qvel = data.time, data.qpos.copy(), data.qvel.copy()
        data.ctrl[:] = pusher_ctrl(k, seed, dt)
        mujoco.mj_step(model, data, nstep=substeps)
        mujoco.mj_kinematics(model, data)
        mujoco.mju_mat2Quat(quat, data.site_xmat[site])
        target = np.concatenate([data.ctrl, [0.1], quat])  # the slider cannot turn: aim at its own heading
        pose = np.concatenate([data.site_xpos[site], quat])
        commands = [{"source": "bench", "step": k}] if k % 10 == 0 else []
        writer.append(StepRecord(time=t, state=state, ctrl=data.ctrl.copy(), ee_target=target[None],
                                 ee_pose=pose[None], qpos=qpos, qvel=qvel, gripper=np.ones(1),
                                 commands=commands, wall_time=time.time()))
        if on_step is not None:
            on_step(k, data)
    return writer.close(success=success, complete=complete)


# -- Gymnasium and LeRobot datasets -------------------------------------------------------------


SMALL = (32, 32)  # width, height: tiny images keep every check fast; the code path is the same
NOT_NORMALIZED = "recommend using a symmetric and normalized space"  # the export's actions are in real units


def checked(env: gymnasium.Env) -> None:
    """check_env with any Gymnasium warning but the normalized-actions advice failing the test."""
    from gymnasium.utils.env_checker import check_env

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(env)
    # ResourceWarnings come from whatever the garbage collector frees meanwhile (other tests' objects)
    problems = [str(w.message) for w in caught
                if NOT_NORMALIZED not in str(w.message) and not issubclass(w.category, ResourceWarning)]
    assert not problems, problems

def open_dataset(out: Path, repo_id: str):
    """The LeRobot dataset an export wrote at `out` (needs the `lerobot` extra)."""
    from lerobot.datasets import LeRobotDataset

    return LeRobotDataset(repo_id, root=out)


def column(ds, key: str) -> np.ndarray:
    """One feature of every frame of a LeRobot dataset, as an array (frames first)."""
    return np.asarray(ds.hf_dataset.with_format("numpy")[key])


# -- a collection campaign in a subprocess (issue 35: tests/test_campaign*.py) ------------------------------

CAMPAIGN_ADMIN, CAMPAIGN_JOIN = "admin-token-1", "join-token-1"


def free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class CampaignProcess:
    """`teleop campaign FILE` in a subprocess (admin and join tokens CAMPAIGN_ADMIN / CAMPAIGN_JOIN),
    asked through its lobby's API."""

    def __init__(self, file: Path, *flags: str) -> None:
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.log_path = file.parent / f"campaign-{self.port}.log"
        self._log = open(self.log_path, "w")
        self.proc = popen_cli(["campaign", str(file), "--port", str(self.port), "--token", CAMPAIGN_ADMIN,
                               "--join-token", CAMPAIGN_JOIN, *flags], self._log)
        wait_until(lambda: self.proc.poll() is not None or self._answers(), 60, "the lobby to answer")
        assert self.proc.poll() is None, self.log()

    def _answers(self) -> bool:
        try:
            return self.ask("GET", f"/api/status?token={CAMPAIGN_ADMIN}")[0] == 200
        except OSError:
            return False

    def ask(self, method: str, path: str, body: dict | None = None) -> tuple[int, dict]:
        import http.client

        conn = http.client.HTTPConnection("127.0.0.1", self.port, timeout=240)
        try:
            conn.request(method, path, body=None if body is None else json.dumps(body))
            response = conn.getresponse()
            return response.status, json.loads(response.read())
        finally:
            conn.close()

    def join(self, name: str) -> tuple[int, dict]:
        return self.ask("POST", f"/api/join?token={CAMPAIGN_JOIN}", {"name": name})

    def status(self) -> dict:
        status, answer = self.ask("GET", f"/api/status?token={CAMPAIGN_ADMIN}")
        assert status == 200, answer
        return answer

    def session(self, session_id: str) -> dict:
        return next(s for s in self.status()["sessions"] if s["id"] == session_id)

    def log(self) -> str:
        if not self._log.closed:
            self._log.flush()
        return self.log_path.read_text()

    def stop(self, sig: int = signal.SIGINT) -> None:
        """Stop as Ctrl-C does (every session saves and ends first)."""
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
            try:
                self.proc.wait(60)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        if not self._log.closed:
            self._log.close()


def campaign_session_status(out: Path, session_id: str) -> dict:
    """A campaign session's status (its SessionStatus, with the rest of teleop serve's status under `serve`
    merged in), {} before its first write."""
    try:
        doc = json.loads((out / ".campaign" / "sessions" / f"{session_id}.status.json").read_text())
    except (OSError, ValueError):
        return {}
    return {**doc.pop("serve", {}), **doc}
