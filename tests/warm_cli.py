"""`teleop` commands forked from a warm process: a fresh process for each, without paying its imports again.

A `teleop export` spends ~7 s of CPU importing LeRobot (torch, torchvision, HF datasets) before it reads a
file (measured: 12.6 s of CPU for a small export from a cold start, 3.4 s forked), a `teleop run` ~1 s importing
MuJoCo and mink (1.5 s against 0.7), and the suite runs a few hundred commands on a 2-core machine. So each
pytest-xdist worker starts one warm process (`python -m tests.warm_cli SOCKET`) that imports those third-party
libraries once, and forks a child for each command: the child is `python -m teleop ARGS` in all that a test can
see (its own pid, the exact environment and working folder asked for, its exit code or signal, stdout and stderr
of its own, stdin from /dev/null, a fresh `__main__`, the interpreter's traceback) and ends as an interpreter does
(threading's shutdown, the atexit hooks, Python's and C's stdio flushed, SystemExit's code, a KeyboardInterrupt's
SIGINT; see _end_like_an_interpreter for what it leaves out).
The project's own modules are never imported in the warm process, so each command loads them as a fresh
interpreter would (lazy imports, import errors and all).

What a forked command cannot show is what happens while the third-party libraries import, and what they read
from the environment then. `run_cli` (tests/support.py) therefore starts a real interpreter whenever the
environment differs from the warm process's in anything but the variables in CALL_TIME_ENV (read by the project
when used, not at import), and the tests of start-up itself (`import teleop` loads no physics, the wheel check)
start their own interpreters. TELEOP_WARM_CLI=0 turns the warm process off: every command a real interpreter. A warm
process that cannot start (a preload that raises) or that dies says so in one line on the test run's stderr, its
log kept, and that worker's commands run in real interpreters.

Three ways in: WarmCli.run / popen (tests/support.py's run_cli, popen_cli, run_script: a console script such as
`lerobot-train` is run as its own file would be), and `python -m tests.warm_cli --client ARGS` (or
`--client-script PATH ARGS`) for a shell script a test runs, whose environment the warm process checks itself.
"""

from __future__ import annotations

import atexit
import builtins
import ctypes
import gc
import importlib
import importlib.machinery
import json
import os
import runpy
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
import traceback
import types
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import NoReturn

# Imported once in the warm process: third-party only (the project's modules load fresh in each command).
PRELOAD = ("numpy", "scipy.spatial.transform", "mujoco", "mink", "h5py", "mcap.writer", "viser", "gymnasium",
           "torch", "lerobot.datasets.lerobot_dataset")
# Variables a command may see changed from the warm process's without a real interpreter: the project reads
# them when used (tempfile's cached folder is reset in the child).
# PYOPENGL_PLATFORM (MuJoCo's EGL module), LD_LIBRARY_PATH (OpenCV's loader) and PYGAME_HIDE_SUPPORT_PROMPT are
# set by imports the warm process does not do; LP_NUM_THREADS is read at the first GL context.
# SHLVL, PWD, OLDPWD and _ are a shell's bookkeeping (a script's commands carry them; no import reads them).
CALL_TIME_ENV = frozenset({"PYTEST_CURRENT_TEST", "TMPDIR", "TELEOP_CACHE", "DISPLAY", "COLUMNS", "LINES",
                           "RAY_TMPDIR", "LP_NUM_THREADS", "SVT_LOG", "PYOPENGL_PLATFORM", "LD_LIBRARY_PATH",
                           "PYGAME_HIDE_SUPPORT_PROMPT", "TELEOP_WARM_SOCKET", "TELEOP_WARM_IGNORE",
                           "SHLVL", "PWD", "OLDPWD", "_"})
# Set while PRELOAD imports, as every command that loads LeRobot sets them first (teleop/cli/export.py's
# quiet_environment: `export`, `eval`, `serve --policy`): HF's libraries read them at import.
IMPORT_ENV = {"HF_HUB_OFFLINE": "1", "HF_DATASETS_DISABLE_PROGRESS_BARS": "1"}
ENV_SWITCH = "TELEOP_WARM_CLI"
SOCKET_ENV = "TELEOP_WARM_SOCKET"  # for the client (a script's $TELEOP): the warm process's socket
IGNORE_ENV = "TELEOP_WARM_IGNORE"  # for the client: its caller's own variables (comma list), read by no import
MESSAGE_MAX = 1 << 20  # bytes: a request (argv, environment, folder) as one SOCK_SEQPACKET message
ROOT = Path(__file__).resolve().parent.parent
# C's fflush(): fflush(NULL) writes out every C stdio stream's buffer
_C_FFLUSH = ctypes.CDLL(None).fflush
_C_FFLUSH.argtypes = [ctypes.c_void_p]


def with_project_path(env) -> dict[str, str]:
    """`env` with the project first on PYTHONPATH, as a test's command runs (its code, not an installed copy)."""
    return {**env, "PYTHONPATH": str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")}


def same_imports(warm_env: dict[str, str], env: dict[str, str], ignore=()) -> bool:
    """Whether imports would see the same in `env` as in the warm process's `warm_env`: equal but for
    CALL_TIME_ENV and the names in `ignore` (a caller's own variables, read by no import). PYTHONPATH compares
    as its folders with repeats dropped (a script that puts the project first again finds the same modules);
    an IMPORT_ENV variable may be unset (a command sets it before it loads LeRobot) or have the value the warm
    process imported with."""
    keys = (warm_env.keys() | env.keys()) - CALL_TIME_ENV - set(ignore) - {"PYTHONPATH"} - IMPORT_ENV.keys()
    return (all(warm_env.get(k) == env.get(k) for k in keys)
            and all(env.get(k) in (None, warm_env.get(k, v)) for k, v in IMPORT_ENV.items())
            and _search_path(warm_env) == _search_path(env))


def _search_path(env: dict[str, str]) -> list[str]:
    """PYTHONPATH's folders in order, each once."""
    return list(dict.fromkeys(env.get("PYTHONPATH", "").split(os.pathsep))) if "PYTHONPATH" in env else []


# -- the warm process -------------------------------------------------------------------------------------


def _reap(conn: socket.socket, pid: int) -> None:
    """Wait for the command `pid` and send its wait status and CPU seconds to the test that asked for it."""
    _, status, usage = os.wait4(pid, 0)
    try:
        conn.send(json.dumps({"status": status, "cpu_s": usage.ru_utime + usage.ru_stime}).encode())
    except OSError:  # the test gave up (a timeout): nobody to tell
        pass
    conn.close()


def _exit_with_parent(parent: int) -> None:
    """End the warm process when the pytest worker that started it is gone (no orphan after a crash)."""
    while os.getppid() == parent:
        time.sleep(1.0)
    os._exit(0)


def _become_command(request: dict, fds: list[int], filters: list) -> NoReturn:
    """In the forked child: become `python -m teleop ARGS` (or `python SCRIPT ARGS`) with the request's folder,
    environment and files, and end as that interpreter would. Never returns to the warm process's loop."""
    try:
        stdin = os.open(os.devnull, os.O_RDONLY)
        os.dup2(stdin, 0)
        os.dup2(fds[0], 1)
        os.dup2(fds[1], 2)
        for fd in (stdin, *fds):
            os.close(fd)
        os.chdir(request["cwd"])
        os.environ.clear()
        os.environ.update(request["env"])
        tempfile.tempdir = None  # gettempdir() reads TMPDIR again
        warnings.filters[:] = filters  # as they were after the imports, before the warm process's own
        signal.signal(signal.SIGINT, signal.default_int_handler)  # as from a terminal (even if the tests ignore it)
        signal.signal(signal.SIGTERM, signal.SIG_DFL)
        if "numpy" in sys.modules:  # a fresh interpreter seeds numpy's global generator from the OS; a fork copies it
            sys.modules["numpy"].random.seed()
        code, interrupted = _run_main(request)
        _end_like_an_interpreter(code, interrupted)
    finally:
        os._exit(70)  # reached only if ending failed in the launcher's own code (EX_SOFTWARE)


def _run_main(request: dict) -> tuple[int, bool]:
    """Run the command in a fresh `__main__` as `python -m teleop` (runpy's _run_module_as_main, as the
    interpreter does) or `python SCRIPT` would; its exit code, and whether an uncaught KeyboardInterrupt ended it.
    An uncaught exception prints the traceback the interpreter prints (the launcher's own frames left out)."""
    main = types.ModuleType("__main__")
    main.__builtins__ = builtins
    sys.modules["__main__"] = main
    try:
        if script := request.get("script"):  # a console script (lerobot-train): as its own interpreter runs it
            sys.argv = [script, *request["argv"]]
            sys.path[0] = os.path.dirname(os.path.realpath(script))  # the script's folder, links resolved
            main.__file__, main.__cached__ = script, None
            main.__loader__ = importlib.machinery.SourceFileLoader("__main__", script)
            exec(compile(Path(script).read_bytes(), script, "exec", dont_inherit=True), main.__dict__)
        else:
            sys.argv = ["-m", *request["argv"]]
            sys.path[0] = os.getcwd()  # `python -m` puts the working folder first
            runpy._run_module_as_main("teleop")
    except SystemExit as exc:  # teleop/__main__.py exits with main()'s code
        return _exit_code(exc.code), False
    except BaseException as exc:
        tb = exc.__traceback__
        while tb is not None and tb.tb_frame.f_code.co_filename == __file__:
            tb = tb.tb_next
        sys.excepthook(type(exc), exc.with_traceback(tb), tb)  # the hook prints the exception's own
        return 1, isinstance(exc, KeyboardInterrupt)
    return 0, False


def _exit_code(value: object) -> int:
    """An interpreter's exit code for `sys.exit(value)`: None 0, an int its low byte (a C long; beyond: 255),
    anything else printed to stderr and 1."""
    if value is None:
        return 0
    if isinstance(value, int):
        return value & 0xFF if -(1 << 63) <= value < 1 << 63 else 0xFF
    print(value, file=sys.stderr)
    return 1


def _end_like_an_interpreter(code: int, interrupted: bool) -> NoReturn:
    """What Python does at exit (Py_FinalizeEx, then Py_RunMain and C's exit), without finalizing every module
    (tearing down torch's and LeRobot's would cost a forked command ~1.5 s of CPU):
    threading._shutdown() (the threading atexits, such as the one that ends a ThreadPoolExecutor's workers, then
    the non-daemon threads joined), the atexit hooks, sys.stdout and sys.stderr flushed (a failure: exit code 120),
    the signals with Python handlers back to their defaults; then after an uncaught KeyboardInterrupt SIGINT
    raised again with its default action (the parent sees "killed by SIGINT"; 130 if that fails), else what the C
    libraries printed flushed (C stdio's buffers, as C's exit() does) and os._exit with the code.
    C's other exit handlers (atexit(3), static destructors) are not run: most belong to libraries the warm process
    loaded and the command may never have used (torch's), and running them took ~1.5 s of every command's end
    (measured: 1.5-2.5 s from the last atexit hook to the test seeing the exit, against 0.35-0.45 s without)."""
    try:
        threading._shutdown()
    except BaseException as exc:  # noqa: BLE001 - the interpreter reports it and goes on ending
        _unraisable(threading, exc)
    atexit._run_exitfuncs()  # each hook's error is reported by it, as at exit
    if not _flush_std_files():
        code = 120
    for sig in signal.valid_signals():  # _PySignal_Fini
        try:
            if callable(signal.getsignal(sig)):
                signal.signal(sig, signal.SIG_DFL)
        except (OSError, ValueError):
            pass
    if interrupted:  # Py_RunMain's exit_sigint: a shell sees the Ctrl-C
        signal.signal(signal.SIGINT, signal.SIG_DFL)
        os.kill(os.getpid(), signal.SIGINT)
        code = 130
    _C_FFLUSH(None)
    os._exit(code)


def _flush_std_files() -> bool:
    """Flush sys.stdout and sys.stderr as the interpreter does at exit (stdout's error reported, as unraisable);
    whether both flushed. The original streams, when a command replaced them, are flushed too (the interpreter's
    module teardown would close them), quietly."""
    ok = True
    for name in ("stdout", "stderr"):
        stream = getattr(sys, name)
        if stream is None or getattr(stream, "closed", False):
            continue
        try:
            stream.flush()
        except Exception as exc:  # noqa: BLE001 - a reader gone (EPIPE), a full disk
            if name == "stdout":
                _unraisable(stream, exc)
            ok = False
    for stream in (sys.__stdout__, sys.__stderr__):
        if stream is not None and stream not in (sys.stdout, sys.stderr) and not stream.closed:
            try:
                stream.flush()
            except Exception:  # noqa: BLE001 - as a closing file's error at teardown: not the exit code's
                pass
    return ok


def _unraisable(where: object, exc: BaseException) -> None:
    """An error the interpreter cannot raise, printed as its default sys.unraisablehook does."""
    try:
        print(f"Exception ignored in: {where!r}", file=sys.stderr)
        traceback.print_exception(exc, file=sys.stderr)
    except Exception:  # noqa: BLE001 - stderr itself is gone: nothing left to tell
        pass


def serve(path: str) -> None:
    """Import PRELOAD, then fork one command per request on the socket at `path` (until the worker ends)."""
    threading.Thread(target=_exit_with_parent, args=(os.getppid(),), daemon=True).start()
    before = dict(os.environ)
    for key, value in IMPORT_ENV.items():
        os.environ.setdefault(key, value)
    for name in PRELOAD:
        try:
            importlib.import_module(name)
        except ImportError as exc:  # an extra not installed: the commands that need it say so themselves
            print(f"warm_cli: not preloaded: {name}: {exc}", file=sys.stderr)
    os.environ.clear()  # the commands get the environment of their request; this one is only for tidiness
    os.environ.update(before)
    filters = list(warnings.filters)
    gc.freeze()  # the imports' objects: never collected, so a command's collections neither walk nor copy them
    listener = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    listener.bind(path)
    listener.listen(16)
    print("ready", flush=True)
    while True:
        conn, _ = listener.accept()
        message, fds, _, _ = socket.recv_fds(conn, MESSAGE_MAX, 2)
        request = json.loads(message)
        if request.get("check") and not same_imports(before, request["env"], request.get("ignore", ())):
            for fd in fds:
                os.close(fd)
            conn.send(json.dumps({"refused": True}).encode())
            conn.close()
            continue
        sys.stdout.flush()
        sys.stderr.flush()
        _C_FFLUSH(None)  # C stdio too: what a library printed here must not come out again at a command's exit
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", DeprecationWarning)  # "multi-threaded, use of fork()": the reapers
            pid = os.fork()
        if pid == 0:
            listener.close()
            conn.close()
            _become_command(request, fds, filters)  # ends the child's interpreter: never returns
        for fd in fds:
            os.close(fd)
        # a pidfd for the test's signals: it names this child only, even once its pid is reaped and reused
        pidfd = _pidfd(pid)
        socket.send_fds(conn, [json.dumps({"pid": pid}).encode()], [] if pidfd is None else [pidfd])
        if pidfd is not None:
            os.close(pidfd)
        threading.Thread(target=_reap, args=(conn, pid), daemon=True).start()


def _pidfd(pid: int) -> int | None:
    """A pidfd for `pid` (Linux 5.3+); None where there is none (then signals go by pid)."""
    try:
        return os.pidfd_open(pid)
    except (AttributeError, OSError):
        return None


def signal_if_running(pid: int, pidfd: int | None, sig: int) -> None:
    """Send `sig` to a forked command unless it has ended (as subprocess.Popen.send_signal: no error then)."""
    try:
        if pidfd is not None:
            signal.pidfd_send_signal(pidfd, sig)
        else:
            os.kill(pid, sig)
    except ProcessLookupError:  # it ended (and was reaped) meanwhile
        pass


# -- the tests' side ----------------------------------------------------------------------------------------


class WarmCli:
    """One warm process for this pytest process, started at its first command, ended with the process."""

    def __init__(self) -> None:
        self.proc: subprocess.Popen | None = None
        self.folder = ""
        self.env: dict[str, str] | None = None  # the warm process's environment (settle_environment)
        self.lock = threading.Lock()
        self.failed = False
        # tests/conftest.py sets it for each test but a unit one (the quick suite would wait for the imports);
        # elsewhere (the bench times real start-ups with tests/browser.py) every command is a real interpreter
        self.wanted = False
        self.forked = 0  # commands forked
        self.cpu_s = 0.0  # CPU seconds of the commands forked for this process (tests/suite_time.py counts them)
        # how a warm process that could not start (or ended) is told: one line on the test run's stderr
        # (tests/conftest.py makes it reach the terminal past pytest's capture)
        self.say: Callable[[str], None] = lambda line: print(line, file=sys.stderr, flush=True)

    def settle_environment(self) -> None:
        """Take the warm process's environment now: os.environ as run_cli completes it. tests/conftest.py calls
        this once the session's variables are set and before any test changes one; otherwise the first command
        does (a test's own variables then make later commands run in real interpreters: slower, never wrong)."""
        self.env = with_project_path(os.environ)

    def _start(self) -> bool:
        """Start the warm process and wait for its imports; False (said on stderr, its log kept) if it fails."""
        if self.env is None:
            self.settle_environment()
        self.folder = tempfile.mkdtemp(prefix="teleop-warm-cli-")
        with open(self.log_path(), "wb") as log:  # the warm process's own output (imports)
            self.proc = subprocess.Popen([sys.executable, "-m", "tests.warm_cli", self.socket_path()],
                                         stdout=subprocess.PIPE, stderr=log, stdin=subprocess.DEVNULL,
                                         env=self.env, cwd=ROOT)
        atexit.register(self.close)
        for line in self.proc.stdout:  # blocks for the imports; a library's own words on stdout are passed over
            if line.strip() == b"ready":
                return True
        self.proc.wait()
        self._gave_up(f"could not start (exit {self.proc.returncode})")
        return False

    def _gave_up(self, what: str) -> None:
        """Say in one line that this worker's commands now run in real interpreters, and why; keep the log."""
        self.failed = True
        try:
            last = [line for line in Path(self.log_path()).read_text(errors="replace").splitlines() if line.strip()]
        except OSError:
            last = []
        why = f": {last[-1].strip()[:200]}" if last else ""
        self.say(f"tests/warm_cli.py: the warm process {what}{why}; this worker's teleop commands run in real "
                 f"interpreters (slower); its log: {self.log_path()}")

    def log_path(self) -> str:
        return os.path.join(self.folder, "log")

    def restore_environment(self) -> None:
        """Undo what a test left changed in os.environ (but CALL_TIME_ENV): a variable an import reads, left
        behind by an in-process command (export's quiet_environment), would make every later command of this
        worker a real interpreter, and would reach the next test's commands however they start."""
        if self.env is None:
            return
        settled = {k: v for k, v in self.env.items() if k != "PYTHONPATH"}
        for key in (os.environ.keys() | settled.keys()) - CALL_TIME_ENV - {"PYTHONPATH"}:
            if key not in settled:
                os.environ.pop(key, None)
            elif os.environ.get(key) != settled[key]:
                os.environ[key] = settled[key]

    def _wrapper(self, folder: Path, name: str, client_args: str) -> str:
        """An executable `folder/name` that runs `python -m tests.warm_cli CLIENT_ARGS "$@"`."""
        wrapper = Path(folder) / name
        wrapper.write_text(f"#!/bin/sh\nexec {sys.executable} -m tests.warm_cli {client_args} \"$@\"\n")
        wrapper.chmod(0o755)
        return str(wrapper)

    def script_command(self, folder: Path, script: str) -> str:
        """An executable in `folder` that runs the console `script` (lerobot-train) forked from this warm process
        (with teleop_command's variables), for a script's $LEROBOT_TRAIN; `script` itself when it cannot serve."""
        if not self.usable_for(self.env or {}):
            return script
        return self._wrapper(folder, Path(script).name, f"--client-script {script}")

    def teleop_command(self, folder: Path) -> tuple[str, dict[str, str]]:
        """An executable that runs `teleop ARGS` forked from this warm process, for a script's $TELEOP, and the
        variables its environment needs (a real `teleop` and none when the warm process cannot serve)."""
        if not self.usable_for(self.env or {}):
            return str(Path(sys.executable).parent / "teleop"), {}
        wrapper = self._wrapper(folder, "teleop", "--client")
        return wrapper, {SOCKET_ENV: self.socket_path(), "PYTHONPATH": self.env["PYTHONPATH"]}

    def socket_path(self) -> str:
        return os.path.join(self.folder, "socket")

    def close(self) -> None:
        """End the warm process (commands it forked run on) and remove its folder, but for the log of one that
        failed (named on stderr when it did)."""
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()
        if self.failed and self.folder:
            Path(self.socket_path()).unlink(missing_ok=True)
        elif self.folder:
            shutil.rmtree(self.folder, ignore_errors=True)

    def usable_for(self, env: dict[str, str], ignore=()) -> bool:
        """Whether a command with `env` may be forked: the warm process runs, and imports would see the same
        (`ignore`: the caller's own variables, read by no import)."""
        if os.environ.get(ENV_SWITCH, "1") == "0" or self.failed or not self.wanted:
            return False
        with self.lock:
            if self.proc is None and not self._start():
                return False
            if self.proc.poll() is not None:  # it died: said once, then every command a real interpreter
                self._gave_up(f"ended (exit {self.proc.returncode})")
                return False
        return same_imports(self.env, env, ignore)

    def popen(self, args: list[str], env: dict[str, str], cwd: Path, stdout: int, stderr: int,
              script: str | None = None) -> WarmPopen:
        """`python -m teleop ARGS` (or the console `script` ARGS) forked from the warm process, writing to the
        file descriptors given."""
        conn = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        conn.connect(self.socket_path())
        request = {"argv": list(args), "env": env, "cwd": str(Path(cwd).resolve()), "script": script}
        socket.send_fds(conn, [json.dumps(request).encode()], [stdout, stderr])
        message, pidfds, _, _ = socket.recv_fds(conn, MESSAGE_MAX, 1)
        self.forked += 1
        return WarmPopen(self, conn, json.loads(message)["pid"], pidfds[0] if pidfds else None,
                         [script, *args] if script else [sys.executable, "-m", "teleop", *args])

    def run(self, args: list[str], env: dict[str, str], cwd: Path, timeout: float,
            script: str | None = None) -> subprocess.CompletedProcess:
        """`python -m teleop ARGS` (or `script` ARGS) forked from the warm process: what
        subprocess.run(capture_output) would give."""
        with tempfile.TemporaryFile() as out, tempfile.TemporaryFile() as err:
            proc = self.popen(args, env, cwd, out.fileno(), err.fileno(), script)
            try:
                proc.wait(timeout)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
                raise
            out.seek(0)
            err.seek(0)
            stdout, stderr = _text(out.read()), _text(err.read())
        return subprocess.CompletedProcess(proc.args, proc.returncode, stdout, stderr)


class WarmPopen:
    """A command forked from the warm process, with what the tests use of subprocess.Popen: pid, poll, wait,
    send_signal, terminate, kill, returncode (-N: ended by signal N). Its output went to the descriptors given."""

    def __init__(self, warm: WarmCli, conn: socket.socket, pid: int, pidfd: int | None, args: list[str]) -> None:
        self.warm, self.conn, self.pid, self.pidfd, self.args = warm, conn, pid, pidfd, args
        self.returncode: int | None = None

    def _ended(self, reply: bytes) -> int:
        self.conn.close()
        self._close_pidfd()
        if not reply:  # the warm process is gone (the worker is ending): the command was its child
            self.returncode = -signal.SIGKILL
            return self.returncode
        status = json.loads(reply)
        self.warm.cpu_s += status["cpu_s"]
        self.returncode = os.waitstatus_to_exitcode(status["status"])
        return self.returncode

    def poll(self) -> int | None:
        if self.returncode is None:
            self.conn.setblocking(False)
            try:
                return self._ended(self.conn.recv(MESSAGE_MAX))
            except BlockingIOError:
                return None
        return self.returncode

    def wait(self, timeout: float | None = None) -> int:
        if self.returncode is None:
            self.conn.settimeout(timeout)
            try:
                return self._ended(self.conn.recv(MESSAGE_MAX))
            except TimeoutError:
                raise subprocess.TimeoutExpired(self.args, timeout) from None
        return self.returncode

    def send_signal(self, sig: int) -> None:
        """As subprocess.Popen's: nothing once the command has ended, even if it ended just now."""
        if self.poll() is None:
            signal_if_running(self.pid, self.pidfd, sig)

    def _close_pidfd(self) -> None:
        if self.pidfd is not None:
            os.close(self.pidfd)
            self.pidfd = None

    def __del__(self) -> None:  # a test that never waited for its command
        try:
            self._close_pidfd()
        except Exception:  # noqa: BLE001 - at interpreter exit, os may already be gone
            pass

    def terminate(self) -> None:
        self.send_signal(signal.SIGTERM)

    def kill(self) -> None:
        self.send_signal(signal.SIGKILL)


def _text(data: bytes) -> str:
    """Bytes as subprocess.run(text=True) gives them: decoded, universal newlines."""
    return data.decode(errors="replace").replace("\r\n", "\n").replace("\r", "\n")


WARM = WarmCli()

def client(args: list[str], script: str | None = None) -> None:
    """`python -m tests.warm_cli --client ARGS`: `teleop ARGS` for a script a test runs (bench/train_eval.sh's
    $TELEOP: see WarmCli.teleop_command), forked from the warm process at $TELEOP_WARM_SOCKET with this
    process's environment, folder, stdout and stderr; its exit code or signal is this process's. When the warm
    process is not there or refuses (the environment differs where imports look), a real interpreter instead."""
    path = os.environ.get(SOCKET_ENV, "")
    if path:
        try:
            conn = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
            conn.connect(path)
        except OSError:
            conn = None
        if conn is not None:
            ignore = [k for k in os.environ.get(IGNORE_ENV, "").split(",") if k]
            request = {"argv": args, "env": dict(os.environ), "cwd": os.getcwd(), "check": True, "ignore": ignore,
                       "script": script}
            socket.send_fds(conn, [json.dumps(request).encode()], [1, 2])
            message, pidfds, _, _ = socket.recv_fds(conn, MESSAGE_MAX, 1)
            reply = json.loads(message)
            if "pid" in reply:
                pid, pidfd = reply["pid"], (pidfds[0] if pidfds else None)
                for sig in (signal.SIGINT, signal.SIGTERM):  # passed on: Ctrl-C or a kill reaches the command
                    signal.signal(sig, lambda number, _frame: signal_if_running(pid, pidfd, number))
                ended = conn.recv(MESSAGE_MAX)
                code = os.waitstatus_to_exitcode(json.loads(ended)["status"]) if ended else -signal.SIGKILL
                if code < 0:  # ended by a signal: so does this process (as a shell reports it), else 128 + N
                    signal.signal(-code, signal.SIG_DFL)
                    os.kill(os.getpid(), -code)
                    code = 128 - code
                os._exit(code)
    if script:
        os.execv(script, [script, *args])
    os.execv(sys.executable, [sys.executable, "-m", "teleop", *args])


if __name__ == "__main__":
    if sys.argv[1] == "--client":
        client(sys.argv[2:])
    elif sys.argv[1] == "--client-script":  # --client-script PATH ARGS: a console script (lerobot-train) likewise
        client(sys.argv[3:], script=sys.argv[2])
    else:
        serve(sys.argv[1])
