"""Issue 19 item 4: the one parallel runner (scenes/workers/runner.py), with real spawned workers.

Generation and export use it (tests/test_generate.py, tests/test_export_parallel.py run
them end to end, Ray included); here its own promises: results in submission order
whatever order tasks finish in, the object sent once per worker, a failure named by
its task, the cancellation token, and draining (workers end their task early and
their results are kept) as against stopping.
"""

from __future__ import annotations

import os
import threading
import time
from pathlib import Path

import pytest

from scenes.workers import Runner

# -- tasks (module level: the spawned workers import this module to find them) -------------


def _late_first(i: int, n: int) -> tuple[int, int]:
    """Earlier tasks take longer, so they finish last."""
    time.sleep(0.05 * (n - i))
    return i, os.getpid()


def _with_shared(shared: dict, i: int) -> int:
    return shared["base"] + i


def _fails_at(i: int, bad: int) -> int:
    if i == bad:
        raise ValueError(f"task {i} fails")
    return i


def _until_cancelled(cancel: threading.Event, bound_s: float) -> str:
    """A long task that ends early when the driver drains the workers (as an export shard does)."""
    return "drained" if cancel.wait(bound_s) else "ran out"


def _sleep(seconds: float) -> int:
    time.sleep(seconds)
    return os.getpid()


# -- tests ------------------------------------------------------------------------------------


def _alive(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


@pytest.mark.parametrize("workers", [1, 2])
def test_results_come_in_submission_order(workers):
    n = 6
    with Runner(workers) as runner:
        runner.wait_started()
        results = list(runner.results(((_late_first, i, n) for i in range(n)), in_flight=n))
    assert [i for i, _ in results] == list(range(n))
    pids = {pid for _, pid in results}
    if workers == 1:
        assert pids == {os.getpid()}  # one worker is this process
    else:
        assert os.getpid() not in pids and len(pids) == 2


def test_the_shared_object_reaches_every_task():
    with Runner(2, shared={"base": 100}) as runner:
        runner.wait_started()
        results = list(runner.results(((_with_shared, runner.shared, i) for i in range(4)), in_flight=4))
    assert results == [100, 101, 102, 103]


def test_a_failing_task_is_named():
    with Runner(2) as runner, pytest.raises(ValueError, match="task 2 fails"):
        list(runner.results(((_fails_at, i, 2) for i in range(4)), in_flight=4))
    assert runner.failed == 2


def test_cancel_token_then_drain_keeps_what_the_workers_return():
    cancel = threading.Event()
    with Runner(2, cancel=cancel) as runner:
        runner.wait_started()
        runner.submit(_late_first, 0, 0)  # done at once
        runner.submit(_until_cancelled, runner.cancel_arg, 60.0)
        runner.wait()
        assert list(runner.ready()) and runner.running == 1
        cancel.set()  # as the CLI's Ctrl-C handler does
        with pytest.raises(KeyboardInterrupt):
            runner.wait()
        drained = runner.drain()
    assert drained == {1: "drained"}  # the first was taken already; the second ended early, its result kept


def test_stop_ends_tasks_in_flight_and_the_workers_go():
    with Runner(2) as runner:
        pids = set(runner.results(((_sleep, 0.0) for _ in range(2)), in_flight=2))
        runner.submit(_sleep, 60.0)
        runner.submit(_sleep, 60.0)
        runner.stop()
    assert runner.running == 0 and pids and not any(_alive(pid) for pid in pids)


def _big_result(marker: str, mbytes: int) -> bytes:
    """A result large enough that sending it back takes many pipe writes (as generated episodes do)."""
    data = os.urandom(mbytes << 20)
    Path(marker).touch()
    return data


@pytest.mark.e2e  # five pools of worker processes, 256 MB results, workers terminated mid-send: many seconds
def test_stop_while_a_result_is_being_sent_back_does_not_hang(tmp_path):
    """A worker terminated half-way through sending a result leaves part of a message in the result pipe;
    the pool's reader must not wait for the rest forever (generate's Ctrl-C would never exit).

    The send window is timed first (marker file to result taken), then workers are stopped at
    points spread across it."""
    def started(name: str) -> Runner:
        runner = Runner(2)
        runner.wait_started()
        runner.submit(_big_result, str(tmp_path / name), 256)
        while not (tmp_path / name).exists():
            time.sleep(0.002)
        return runner

    with started("timed") as runner:
        t0 = time.perf_counter()
        runner.wait()
        window_s = time.perf_counter() - t0
    hung = []
    for fraction in (0.2, 0.4, 0.6, 0.8):
        runner = started(f"stopped-{fraction}")
        time.sleep(fraction * window_s)
        runner.stop()
        closer = threading.Thread(target=runner.close, daemon=True)
        closer.start()
        closer.join(30.0)
        if closer.is_alive():
            hung.append(fraction)
    assert not hung, f"close() hung after stop() at {hung} of the {window_s:.2f} s send window"
