"""The warm process that forks `teleop` commands for the tests (tests/warm_cli.py) gives what a real
interpreter gives: the same exit code, stdout and stderr, the folder and environment asked for, a timeout
that ends the command, the same ending (threads, atexit hooks, SystemExit, an uncaught Ctrl-C, C's stdio) and
the same files from representative commands; it steps aside when the environment could change what the imports
see, and says so when it cannot start; a signal to a command that has ended is no error."""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from tests.support import PICK, ROOT, assert_one_line_error, popen_cli, run_cli, wait_until
from tests.warm_cli import WARM, WarmCli, signal_if_running, with_project_path

pytestmark = pytest.mark.e2e  # starts the warm process (LeRobot's imports: seconds of CPU)


def fresh(*args: str, cwd=ROOT, env: dict | None = None) -> subprocess.CompletedProcess:
    """`teleop ARGS` in a real interpreter, as run_cli would without the warm process."""
    env = {**os.environ, **(env or {}), "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    return subprocess.run([sys.executable, "-m", "teleop", *args], capture_output=True, text=True, env=env, cwd=cwd,
                          timeout=300)


def test_a_forked_command_answers_as_a_real_interpreter_does(tmp_path):
    forked_before = WARM.forked
    for args in (("run", "--bogus"), ("robots", "--json"), ("inspect", str(tmp_path / "missing.mcap"), "--json")):
        warm, real = run_cli(*args), fresh(*args)
        assert (warm.returncode, warm.stdout, warm.stderr) == (real.returncode, real.stdout, real.stderr), args
    assert WARM.forked == forked_before + 3, "the commands were not forked from the warm process"
    assert WARM.cpu_s > 0


def test_a_forked_command_works_in_the_folder_and_environment_asked_for(tmp_path):
    before = WARM.forked
    scratch = tmp_path / "tmp"
    scratch.mkdir()
    summary = json.loads(run_cli("run", "--device", f"script:{PICK}", "--record", "rel", "--json", cwd=tmp_path,
                                 env={"TMPDIR": str(scratch)}).stdout)
    assert summary["success"] is True and (tmp_path / "rel" / "episode_000000.mcap").is_file()
    assert WARM.forked == before + 1
    # a variable an import could read: a real interpreter, which sees it
    result = run_cli("run", "--bogus", env={"HF_LEROBOT_HOME": str(tmp_path)})
    assert result.returncode == 2 and WARM.forked == before + 1
    assert not WARM.usable_for({**WARM.env, "PYTHONPATH": str(tmp_path)})
    assert WARM.usable_for({**WARM.env, "TMPDIR": str(scratch), "PYTEST_CURRENT_TEST": "x"})


def test_a_timeout_ends_the_forked_command(tmp_path):
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    with pytest.raises(subprocess.TimeoutExpired):
        run_cli("serve", "--port", str(port), timeout=3)

    def port_free() -> bool:
        with socket.socket() as s:
            try:
                s.bind(("127.0.0.1", port))
            except OSError:
                return False
            return True

    wait_until(port_free, 30, "the timed-out server to end and free its port")


# -- ending as an interpreter ends ------------------------------------------------------------------------------

ENDING = textwrap.dedent('''
    """How a script ends, by its first argument: the forked child and a real interpreter must agree."""
    import atexit, concurrent.futures, ctypes, os, sys, threading, time

    import __main__

    print(__name__, __main__.__file__ == __file__ == sys.argv[0], sys.path[0] == os.path.dirname(__file__))
    atexit.register(print, "atexit hook")
    mode = sys.argv[1]
    if mode == "pool":  # a live pool never shut down, a non-daemon thread still working: both end before the hooks
        pool = concurrent.futures.ThreadPoolExecutor(1)
        print(pool.submit(str.upper, "pool task").result())
        threading.Thread(target=lambda: (time.sleep(0.3), print("thread done", flush=True))).start()
    elif mode == "c-stdio":  # in C's stdout buffer until C's exit() flushes it, after Python's own
        ctypes.CDLL(None).printf(b"from C\\n")
    elif mode == "exit-message":
        sys.exit("no such thing")
    elif mode == "exit-code":
        sys.exit(300)
    elif mode == "error":
        raise ValueError("bad value")
    elif mode == "interrupt":  # uncaught: the traceback, the hooks, then killed by SIGINT (a shell sees the Ctrl-C)
        raise KeyboardInterrupt
''')


@pytest.mark.parametrize("mode, code", [("pool", 0), ("c-stdio", 0), ("exit-message", 1), ("exit-code", 44),
                                        ("error", 1), ("interrupt", -signal.SIGINT)])
def test_a_forked_script_ends_as_its_interpreter_does(tmp_path, mode, code):
    script = tmp_path / "ending.py"
    script.write_text(ENDING)
    env = with_project_path(os.environ)
    assert WARM.usable_for(env)
    warm = WARM.run([mode], env, tmp_path, timeout=60, script=str(script))
    real = subprocess.run([sys.executable, str(script), mode], capture_output=True, text=True, env=env, cwd=tmp_path,
                          timeout=60)
    assert (warm.returncode, warm.stdout, warm.stderr) == (real.returncode, real.stdout, real.stderr)
    assert real.returncode == code and real.stdout.startswith("__main__ True True\n")
    expected = {"pool": "POOL TASK\nthread done\natexit hook\n", "c-stdio": "from C\n"}.get(mode, "atexit hook\n")
    assert expected in real.stdout and "atexit hook\n" in real.stdout


def test_a_warm_process_that_cannot_start_says_so_and_keeps_its_log(tmp_path):
    shadow = tmp_path / "shadow" / "numpy"  # the first preload raises (not an ImportError: a broken install)
    shadow.mkdir(parents=True)
    (shadow / "__init__.py").write_text("raise RuntimeError('numpy is broken here')\n")
    broken = WarmCli()
    broken.wanted = True
    broken.env = {**WARM.env, "PYTHONPATH": f"{shadow.parent}{os.pathsep}{WARM.env['PYTHONPATH']}"}
    said: list[str] = []
    broken.say = said.append
    try:
        assert not broken.usable_for(broken.env) and not broken.usable_for(broken.env)
    finally:
        broken.close()
    assert len(said) == 1 and "could not start" in said[0] and "numpy is broken here" in said[0], said
    log = Path(broken.log_path())
    assert said[0].endswith(str(log)) and "Traceback" in log.read_text()
    shutil.rmtree(log.parent)


def test_a_signal_to_a_command_that_has_ended_is_no_error(tmp_path):
    with open(tmp_path / "out", "wb") as out:
        proc = popen_cli(["run", "--bogus"], out)
        wait_until(lambda: not Path(f"/proc/{proc.pid}").exists(), 60, "the command to end and be reaped")
        if proc.pidfd is not None:  # ended and reaped, its pid free for another process: nothing sent, no error
            signal_if_running(proc.pid, proc.pidfd, signal.SIGTERM)
        signal_if_running(proc.pid, None, 0)  # by pid, where there is no pidfd: no error either
        assert proc.wait(60) == 2
        proc.send_signal(signal.SIGTERM)
        proc.kill()
    assert proc.returncode == 2


# -- representative commands, forked and in a real interpreter ----------------------------------------------------

TIMING = re.compile(r"\b\d+(\.\d+)? (s|frames/s)\b")  # wall times in a command's words


def same_files(a: Path, b: Path, exact: bool = True) -> list[str]:
    """The files under `a` and `b`, named alike (relative paths); with `exact`, byte for byte alike."""
    names = sorted(str(p.relative_to(a)) for p in a.rglob("*") if p.is_file())
    assert names == sorted(str(p.relative_to(b)) for p in b.rglob("*") if p.is_file())
    if exact:
        assert [n for n in names if (a / n).read_bytes() != (b / n).read_bytes()] == []
    return names


def same_episode(a: Path, b: Path) -> None:
    from replay import load_episode

    x, y = load_episode(a), load_episode(b)
    assert (x.steps, x.meta.complete, x.meta.success, x.meta.seed) == (y.steps, y.meta.complete, y.meta.success, y.meta.seed)
    for name in ("time", "state", "ctrl", "ee_target", "qpos"):
        assert np.array_equal(getattr(x, name), getattr(y, name)), name


def test_representative_commands_end_alike_forked_and_in_a_real_interpreter(tmp_path, tmp_script):
    """A `--json` run recording HDF5, an export, a bad input (exit 2), a run stopped by SIGINT: the same exit code,
    stdout (but wall times) and files, forked from the warm process and in a real interpreter."""
    script = tmp_script([{"duration": 0.5, "move": [0.0, 0.0, 0.02]}, {"duration": 0.2, "gripper": "close"}])
    sides = {"warm": tmp_path / "warm", "real": tmp_path / "real"}
    for folder in sides.values():
        folder.mkdir()

    def both(*args: str) -> dict[str, subprocess.CompletedProcess]:
        forked = WARM.forked
        done = {"warm": run_cli(*args, cwd=sides["warm"]), "real": fresh(*args, cwd=sides["real"])}
        assert WARM.forked == forked + 1, "not forked from the warm process"
        assert done["warm"].returncode == done["real"].returncode, {k: v.stderr[-2000:] for k, v in done.items()}
        return done

    done = both("run", "--device", f"script:{script}", "--record", "rec", "--format", "hdf5", "--json")
    runs = [json.loads(d.stdout) for d in done.values()]
    assert done["warm"].returncode == 0, done["warm"].stderr[-2000:]
    assert runs[0].pop("wall_seconds") > 0 and runs[1].pop("wall_seconds") > 0
    assert runs[0] == runs[1] and runs[0]["files"] == ["rec/episode_000000.hdf5"]
    same_files(sides["warm"] / "rec", sides["real"] / "rec", exact=False)  # the start time differs
    same_episode(sides["warm"] / "rec/episode_000000.hdf5", sides["real"] / "rec/episode_000000.hdf5")

    done = both("export", str(sides["warm"] / "rec"), "--out", "ds", "--repo-id", "t/warm", "--cameras", "none")
    assert done["warm"].returncode == 0 and "Traceback" not in done["warm"].stderr
    assert TIMING.sub("N", done["warm"].stdout) == TIMING.sub("N", done["real"].stdout)
    same_files(sides["warm"] / "ds", sides["real"] / "ds")

    done = both("run", "--device", "script:missing.json")
    assert_one_line_error(done["warm"], "missing.json")
    assert (done["warm"].stdout, done["warm"].stderr) == (done["real"].stdout, done["real"].stderr)

    stopped = {}
    for side, folder in sides.items():  # Ctrl-C once two episodes are saved: exit 130, what was recorded kept
        argv = ["run", "--device", f"script:{script}", "--episodes", "200", "--no-verify", "--record", "sig", "--json"]
        with open(folder / "sig.out", "wb") as out, open(folder / "sig.err", "wb") as err:
            proc = popen_cli(argv, out, cwd=folder, stderr=err.fileno()) if side == "warm" else popen_fresh(argv, out, err, folder)
            try:
                wait_until(lambda: proc.poll() is not None or (folder / "sig/episode_000002.mcap").exists(), 120,
                           "two episodes to be saved")
                proc.send_signal(signal.SIGINT)
                proc.wait(60)
            finally:
                proc.kill()
        stopped[side] = proc.returncode, json.loads((folder / "sig.out").read_text())
    assert stopped["warm"][0] == stopped["real"][0] == 130
    summaries = [summary for _, summary in stopped.values()]
    assert all(s["interrupted"] for s in summaries) and {*summaries[0]} == {*summaries[1]}
    saved = min(s["episodes"] for s in summaries)
    assert saved >= 1 and summaries[0]["per_episode"][:saved] == summaries[1]["per_episode"][:saved]
    for i in range(saved):
        same_episode(sides["warm"] / f"sig/episode_{i:06d}.mcap", sides["real"] / f"sig/episode_{i:06d}.mcap")


def popen_fresh(args: list[str], out, err, cwd: Path) -> subprocess.Popen:
    """popen_cli in a real interpreter, with Ctrl-C as from a terminal (as a forked command has it)."""
    env = with_project_path(os.environ)
    return subprocess.Popen([sys.executable, "-m", "teleop", *args], stdout=out, stderr=err, env=env, cwd=cwd,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
