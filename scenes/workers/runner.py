"""One way to run tasks in parallel: this process, local worker processes, or Ray tasks.

Used by generation (batches of seeds) and parallel export (shards of episodes).
Results are taken in submission order, whatever order tasks finish in, so a job
gives the same output with 1, 2 or 20 workers. The driver submits as it goes
(generation hands out only the attempts still needed), waits for tasks to finish,
and takes what is ready in order.

Stopping: `wait` raises KeyboardInterrupt when the cancellation token is set (the
CLI's Ctrl-C handler sets it) or a Ctrl-C reaches a library caller; the caller then
either `stop`s the tasks in flight at once, or `drain`s them: local workers see the
request (`worker.cancel_token()`), end their task early keeping what is whole, and
their results are collected. Local workers watch the driver and exit when it dies
(scenes/workers/worker.py); Ray tasks belong to the driver and Ray cancels them
when it goes.
"""

from __future__ import annotations

import contextlib
import multiprocessing
import os
import tempfile
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from typing import Any

from scenes.workers import worker
from scenes.workers.cluster import ClusterError, connect_ray
from scenes.workers.interrupts import is_cancelled
from scenes.errors import first_line

POLL_S = 0.25  # how often a wait looks at the cancellation token and calls its poll (s)
UNIX_SOCKET_PATH_MAX = 107  # bytes: the longest path an AF_UNIX socket may bind on Linux
STOP_GRACE_S = 5.0  # how long a stopped worker has to exit on SIGTERM before it is killed (s)


class WorkerLost(ClusterError):
    """A local worker process or a Ray worker/node died under a task (one line)."""


def worker_context(preload: tuple[str, ...] = ()) -> multiprocessing.context.BaseContext:
    """How local workers start: forked from multiprocessing's fork server, a fresh interpreter that imports
    `preload` and nothing else. Nothing of the driver (a GL context, MuJoCo state, its threads) crosses a fork,
    as with spawn, but the imports are paid once per job instead of once per worker (seconds each for LeRobot).
    The server takes the preload list of the first job that starts it and lives as long as this process.
    Its socket lives in the temporary folder; where that folder's path is too long for a socket's address
    (a deep TMPDIR), the workers are spawned instead: each imports for itself."""
    if len(os.path.join(tempfile.gettempdir(), "pymp-12345678", "listener-12345678")) > UNIX_SOCKET_PATH_MAX:
        return multiprocessing.get_context("spawn")
    ctx = multiprocessing.get_context("forkserver")
    if preload:
        ctx.set_forkserver_preload(list(preload))
    return ctx


class Runner:
    """Tasks on `workers` local processes (1: this process) or on the Ray cluster at `ray`.

    shared: an object every task needs (sent once per worker, or put in Ray's object
    store once); a task names it in its arguments as `runner.shared`.
    setup(*setup_args): runs once in each local worker process as it starts (imports,
    a first build), before start-up counts as done; not in this process, not on Ray.
    ray_options: for `ray.remote` (num_cpus is 1 unless given).
    cancel: the cancellation token `wait` watches.
    processes: local tasks run in worker processes even when there is one (else it is this process).
    preload: modules (the tasks' own, and the heavy libraries they load) imported once by the server process
    the local workers are forked from, so that N workers pay those imports once, not N times; not on Ray.
    """

    def __init__(self, workers: int = 1, ray: str | None = None, shared: Any = None,
                 setup: Callable[..., None] | None = None, setup_args: tuple = (),
                 ray_options: dict | None = None, cancel: threading.Event | None = None,
                 processes: bool = False, preload: tuple[str, ...] = ()) -> None:
        self.cancel = cancel
        self.t_start = time.perf_counter()
        self.startup_s = 0.0
        self._futures: dict[int, Any] = {}  # index -> Future or ObjectRef, not finished yet
        self._done: dict[int, Any] = {}  # index -> result, finished and not yet taken
        self._calls: dict[int, tuple] = {}  # in this process: index -> (fn, args), not run yet
        self._next = 0  # index of the next task submitted
        self._taken = 0  # index of the next result to take
        self.failed: int | None = None  # index of the task whose failure was raised
        self._pool: ProcessPoolExecutor | None = None
        self._ray = None
        self._remote: dict[Callable, Any] = {}
        self._ray_options = {"num_cpus": 1, **(ray_options or {})}
        self._cancel_workers = None
        if ray is not None:
            self._ray = connect_ray(ray)
            self.backend = "ray"
            cpus = max(1, int(self._ray.cluster_resources().get("CPU", 1)))
            self.workers = workers if workers > 1 else cpus
            self._shared = self._ray.put(shared) if shared is not None else None
        else:
            self.backend = "local"
            self.workers = max(1, workers)
            self._shared = shared
            if self.workers > 1 or processes:
                ctx = worker_context(preload)
                self._cancel_workers = ctx.Event()
                self._pool = ProcessPoolExecutor(
                    self.workers, mp_context=ctx, initializer=worker.start,
                    initargs=(os.getpid(), self._cancel_workers, shared, setup, setup_args))
                self._ready = [self._pool.submit(worker.ready, 0.2) for _ in range(self.workers)]

    # -- start-up ------------------------------------------------------------

    def wait_started(self) -> float:
        """Block until every local worker has started (fork server, imports, setup); the seconds since creation."""
        if self._pool is not None:
            pending = set(self._ready)
            while pending:
                done, pending = wait(pending, timeout=POLL_S)
                for fut in done:
                    self._raise_lost(fut, "starting")
                if is_cancelled(self.cancel):
                    raise KeyboardInterrupt
        self.startup_s = round(time.perf_counter() - self.t_start, 3)
        return self.startup_s

    # -- submitting and taking -------------------------------------------------

    @property
    def shared(self) -> Any:
        """The shared object as a task argument: the marker locally, the object ref on Ray, itself in-process."""
        return worker.SHARED if self._pool is not None else self._shared

    @property
    def cancel_arg(self) -> threading.Event | Any:
        """A task argument that is, where the task runs, a token set when the driver drains the tasks:
        the worker's own locally, this runner's token in this process; None on Ray (tasks are cancelled)."""
        if self._pool is not None:
            return worker.CANCEL
        return None if self._ray is not None else self.cancel

    def submit(self, fn: Callable[..., Any], *args: Any) -> int:
        """Queue fn(*args) (a module-level function, for pickling); returns its index among the submitted."""
        index = self._next
        self._next += 1
        if self._pool is not None:
            self._futures[index] = self._pool.submit(worker.call, fn, args)
        elif self._ray is not None:
            task = self._remote.get(fn)
            if task is None:
                task = self._remote[fn] = self._ray.remote(**self._ray_options)(fn)
            self._futures[index] = task.remote(*args)
        else:
            self._calls[index] = (fn, args)
        return index

    @property
    def running(self) -> int:
        """Tasks submitted and not finished."""
        return len(self._futures) + len(self._calls)

    @property
    def pending(self) -> int:
        """Tasks submitted whose results are not yet taken."""
        return self._next - self._taken

    def wait(self, poll: Callable[[], None] | None = None) -> None:
        """Until at least one more task has finished (at once when none is running).

        Raises KeyboardInterrupt when the token is set, and a task's own exception (or
        WorkerLost) as soon as its failure is seen, with `failed` naming it.
        """
        if is_cancelled(self.cancel):
            raise KeyboardInterrupt
        if self._calls:  # this process: run the oldest
            index = min(self._calls)
            fn, args = self._calls.pop(index)
            try:
                self._done[index] = fn(*args)
            except BaseException:
                self.failed = index
                raise
            return
        while self._futures:
            finished = self._poll_finished(POLL_S)
            if poll is not None:
                poll()
            if finished:
                return
            if is_cancelled(self.cancel):
                raise KeyboardInterrupt

    def ready(self) -> Iterator[Any]:
        """The finished results, in submission order, up to the first one not finished."""
        while self._taken in self._done:
            result = self._done.pop(self._taken)
            self._taken += 1
            yield result

    def results(self, calls: Iterable[tuple], in_flight: int, poll: Callable[[], None] | None = None) -> Iterator[Any]:
        """Each call's result in order: calls are (fn, *args), submitted lazily, at most `in_flight` running."""
        calls = iter(calls)
        more = True
        while True:
            while more and self.running < max(1, in_flight):
                call = next(calls, None)
                if call is None:
                    more = False
                    break
                self.submit(*call)
            if not self.pending:
                return
            self.wait(poll)
            yield from self.ready()

    def _poll_finished(self, timeout: float) -> bool:
        """Move finished tasks to _done; raise the first failure. True if any finished."""
        if self._pool is not None:
            done, _ = wait(list(self._futures.values()), timeout=timeout, return_when=FIRST_COMPLETED)
            finished = [i for i, f in self._futures.items() if f in done]
        else:
            refs = list(self._futures.values())
            done, _ = self._ray.wait(refs, num_returns=1, timeout=timeout)
            done = set(done)
            finished = [i for i, r in self._futures.items() if r in done]
        for index in sorted(finished):
            handle = self._futures.pop(index)
            try:
                self._done[index] = self._result(handle)
            except BaseException:
                self.failed = index
                raise
        return bool(finished)

    def _result(self, handle: Any) -> Any:
        if self._pool is not None:
            self._raise_lost(handle, "running a task")
            return handle.result()
        ray = self._ray
        try:
            return ray.get(handle)
        except ray.exceptions.RayTaskError as exc:
            if isinstance(exc.cause, Exception):
                raise exc.cause from None  # the task's own error, as the local backend gives it
            raise WorkerLost(f"a Ray task failed: {first_line(exc)[:200]}") from None
        except ray.exceptions.RayError as exc:  # a worker or node lost, or the task cancelled
            raise WorkerLost(f"a Ray worker or node was lost: {first_line(exc)[:200]}") from None

    @staticmethod
    def _raise_lost(fut: Future, doing: str) -> None:
        exc = fut.exception()
        if isinstance(exc, BrokenProcessPool):
            raise WorkerLost(f"a worker process died {doing}") from None

    # -- stopping ---------------------------------------------------------------

    def stop(self) -> None:
        """End the tasks in flight now: their work is lost (local workers terminated, Ray tasks cancelled)."""
        self._calls.clear()
        if self._pool is not None:
            for fut in self._futures.values():
                fut.cancel()
            # ProcessPoolExecutor.terminate_workers() comes with Python 3.14; until then, its process table.
            processes = list((getattr(self._pool, "_processes", None) or {}).values())
            for process in processes:
                with contextlib.suppress(Exception):
                    process.terminate()
            # A worker terminated half-way through sending a result (a generated episode is megabytes)
            # leaves part of a message in the result pipe, and the pool's reader thread would wait for
            # the rest forever, so `close` would never return. This process holds the pipe's write end
            # too: closed here, the reader meets the pipe's end once the workers are gone, and the pool
            # shuts down as broken.
            for process in processes:
                with contextlib.suppress(Exception):
                    process.join(STOP_GRACE_S)
                    if process.is_alive():
                        process.kill()
            writer = getattr(getattr(self._pool, "_result_queue", None), "_writer", None)
            if writer is not None:
                with contextlib.suppress(OSError):
                    writer.close()
        elif self._ray is not None:
            for ref in self._futures.values():
                with contextlib.suppress(Exception):
                    self._ray.cancel(ref, force=True)
        self._futures.clear()

    def drain(self) -> dict[int, Any]:
        """Ask the running tasks to end early and collect what they return; tasks not started never run.

        Local workers see the request in `worker.cancel_token()`; Ray tasks are cancelled
        (what finished before is kept). Returns {index: result} for every task that
        finished without an error, taken or not. A Ctrl-C meanwhile does not cut it short.
        """
        self._calls.clear()
        if self._pool is not None:
            self._cancel_workers.set()
            for fut in self._futures.values():
                fut.cancel()
            while True:
                try:
                    wait([f for f in self._futures.values() if not f.cancelled()])
                    break
                except KeyboardInterrupt:
                    continue
            for index, fut in list(self._futures.items()):
                if not fut.cancelled() and fut.exception() is None:
                    self._done[index] = fut.result()
            self._futures.clear()
        else:
            self.stop()
        return dict(self._done)

    def close(self) -> None:
        """Let the worker processes go (after stop or drain, or once all is taken); the Ray cluster stays up."""
        if self._pool is None:
            return
        pool, self._pool = self._pool, None
        while True:
            try:
                pool.shutdown(wait=True, cancel_futures=True)
                return
            except KeyboardInterrupt:  # a library caller's Ctrl-C: the workers must still be joined
                continue

    def __enter__(self) -> Runner:
        return self

    def __exit__(self, kind, exc, tb) -> None:
        if kind is not None:
            self.stop()  # an error or an interrupt: the tasks in flight (or starting) are of no use now
        self.close()
