"""`teleop generate`: many demonstrations from a few, on local worker processes or a Ray cluster.

The driver loads and annotates the sources once, then hands out batches of
seeds. A worker (a process of its own, or a Ray task on any machine) builds each
seed's scene, runs one generated attempt (teleop.generate.plan) through the same
Session and loop as a person's episode, records it, checks it replays bit for
bit, and returns the episode's bytes: the driver alone writes files, so a
cluster needs no shared file system.

Results are taken in seed order whatever order workers finish in, so the same
sources and seed give the same episodes with 1, 2 or 20 workers.
"""

from __future__ import annotations

import itertools
import math
import os
import shutil
import sys
import threading
import time
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

from recorder.disk import NotEnoughSpace, WriteError, check_free_space, write_bytes_whole, write_error
from replay.episode import EpisodeError, find_episodes, load_episode
from replay.subtasks.annotate import auto_subtasks
from replay.subtasks.sidecar import SIDECAR_SUFFIX, AnnotationError, read_subtasks, write_subtasks
from scenes.errors import TeleopError, first_line
from scenes.tasks.placement import PlacementError
from scenes.tasks.registry import TASK_FILE_KEY, task_for_episode
from scenes.vary.variation import Variation
from scenes.workers import Runner, connect_ray
from teleop.generate.arms import ArmSegments, ArmsPlanDevice, arm_refs, choose_arm_segments, cut_arms, generated_subtasks
from teleop.generate.plan import SETTLE_S, PlanDevice, Segment, choose_segments, segments_of
from teleop.generate.resume import Done, Journal, run_identity
from teleop.generate.scratch import scratch_dir, sweep_stale
from teleop.control.loop import run_episode
from teleop.control.recording import Recorder
from teleop.control.session import Session

GENERATOR = "teleop.generate.generator"
GENERATOR_VERSION = 1
FORMATS = ("mcap", "hdf5")
# Why an attempt failed, as the journal and the summary's `failures` count it: the task could not place
# its objects for the seed (the file's regions are too tight for it), or the run ended without success.
PLACEMENT, TASK_NOT_DONE = "placement", "task_not_done"


class GenerateError(TeleopError, ValueError):
    """Sources or options that cannot generate (mixed scenes, no grasp, a bad Ray address, ...)."""


@dataclass(frozen=True)
class SourceDemo:
    """A source episode cut into its subtask segments."""

    name: str
    segments: tuple[Segment, ...]  # a two-arm source: every arm's, one arm after the other
    arms: ArmSegments | None = None  # a two-arm source: its segments per arm (teleop.generate.arms)


@dataclass(frozen=True)
class Job:
    """What every worker needs: the scene and the sources (sent once per worker)."""

    scene: str
    robot: str
    control_hz: float
    sources: tuple[SourceDemo, ...]
    formats: tuple[str, ...]
    keep_failures: bool
    settle_s: float = SETTLE_S
    task_file: Mapping[str, Any] | None = None  # the sources' embedded task file (scenes.tasks.registry.TASK_FILE_KEY), if any
    variation: Variation | None = None  # physics drawn per seed into each episode's model (scenes.vary.physics)
    constraints: tuple = ()  # a two-arm task's constraints, arms by index (teleop.generate.arms.arm_refs)
    source_per_arm: bool = False  # a two-arm task: each arm chooses its own sources (else one source for all)

    def session(self, seed: int) -> Session:
        """The scene for `seed`: from the task file the sources embed when they do, else by name."""
        task = task_for_episode(self.scene, {TASK_FILE_KEY: self.task_file} if self.task_file else None)
        return Session(scene=task, robot=self.robot, seed=seed, control_hz=self.control_hz, variation=self.variation)

    @property
    def max_steps(self) -> int:
        """A bound on one attempt's ticks: the longest source, twice, plus settling."""
        longest = max(sum(len(s.poses) for s in src.segments) for src in self.sources)
        return 2 * longest + int(math.ceil((self.settle_s + 10.0) * self.control_hz))


@dataclass
class Attempt:
    """One seed's result, as a worker returns it."""

    seed: int
    index: int  # episode index the files carry (its position among the attempts, after the directory's episodes)
    success: bool
    steps: int
    sources: tuple[str, ...]
    bit_exact: bool | None = None
    files: list[tuple[str, bytes]] = field(default_factory=list)  # (file name, bytes); only what is kept
    error: str = ""  # a seed whose scene could not be placed: the task file's one line (counted as a failure)
    reason: str = ""  # why it failed (PLACEMENT, TASK_NOT_DONE); "" for a success


@dataclass
class GenerateSummary:
    attempts: int = 0
    successes: int = 0
    success_rate: float = 0.0
    episodes_per_min: float = 0.0  # kept episodes per minute of wall time, workers' start-up excluded
    workers: int = 1
    backend: str = "local"  # "local" or "ray"
    files: list[str] = field(default_factory=list)
    failures_kept: int = 0
    not_bit_exact: int = 0
    seconds: float = 0.0  # wall time in all
    startup_s: float = 0.0  # of which starting the workers (fork server, imports) or joining Ray
    seeds: list[int] = field(default_factory=list)  # seeds of the kept successes
    stopped_early: str = ""  # why fewer than asked were kept ("" when all were)
    interrupted: bool = False  # Ctrl-C: what was kept until then stays
    resumed_from: int = 0  # kept episodes of this run already in --out when it started (a re-run resumes)
    seeds_skipped: list[int] = field(default_factory=list)  # seeds already kept or failed there: not run again
    error: str = ""  # the write error that stopped it ('<file>: <cause>'), "" when none
    failures: dict[str, int] = field(default_factory=dict)  # failed attempts by reason (PLACEMENT, TASK_NOT_DONE)
    placement_error: str = ""  # the task file's line for the first seed it could not place, "" when none

    def to_json(self) -> dict:
        return asdict(self)

    def line(self) -> str:
        out = (f"generated {self.successes} episodes in {self.attempts} attempts "
               f"({self.success_rate:.0%} success, {self.episodes_per_min:.1f} episodes/min, "
               f"{self.workers} {'Ray' if self.backend == 'ray' else 'local'} workers)")
        out += f"; resumed from {self.resumed_from} episodes already there" if self.seeds_skipped else ""
        out += ("; failed: " + ", ".join(f"{n} {why.replace('_', ' ')}" for why, n in sorted(self.failures.items()))
                if self.failures else "")
        out += f"; {self.stopped_early}" if self.stopped_early else ""
        return out + ("; interrupted" if self.interrupted else "")


# -- sources --------------------------------------------------------------------


def load_sources(paths: Iterable[str | Path], log: Callable[[str], None] | None = None) -> tuple[Job, list[SourceDemo]]:
    """Load, check and cut the source episodes; returns (a Job with scene, robot and rate, the sources).

    Every source is checked before any is annotated, so a bad one is the only
    thing said. Sources without stored annotations are annotated automatically
    (and the annotations saved beside them when the folder is writable).
    """
    files = find_episodes(paths)
    if not files:
        raise GenerateError("no source episodes given")
    episodes = []
    kinds: dict[tuple[str, str, float], str] = {}
    for path in files:
        try:
            ep = load_episode(path)
        except EpisodeError as exc:
            raise GenerateError(str(exc)) from None
        kinds.setdefault((ep.meta.scene, ep.meta.robot, ep.meta.control_hz), path.name)
        if len(kinds) > 1:
            found = ", ".join(f"{name} is {s}/{r} at {hz:g} Hz" for (s, r, hz), name in kinds.items())
            raise GenerateError(f"sources must share one scene, robot and control rate: {found}")
        task = _task_of(ep)
        two_arm = task is not None and any(spec.arm for spec in task.subtasks)  # its subtasks are per arm
        if len(ep.meta.arms) != 1 and not two_arm:
            raise GenerateError(f"{path.name}: generation drives one arm; this episode has {len(ep.meta.arms)}")
        episodes.append(ep)
    annotated = [(ep, read_subtasks(ep.path, ep.steps)) for ep in episodes]
    found = [(ep, subtasks or auto_subtasks(ep), subtasks is None) for ep, subtasks in annotated]
    constraints = task.constraints if two_arm else ()
    sources: list[SourceDemo] = []
    for ep, subtasks, auto in found:
        if auto:
            try:
                write_subtasks(ep.path, subtasks, ep.steps, by="auto")
            except OSError:
                pass  # a read-only source: the annotations are used, not kept
            if log is not None:
                log(f"{ep.path.name}: annotated automatically ({_objects(subtasks)})")
        if not two_arm:
            sources.append(SourceDemo(str(ep.path), tuple(segments_of(ep, subtasks))))
            continue
        if not all(s.arm for s in subtasks):
            raise GenerateError(f"{ep.path.name}: a two-arm task's source must be annotated per arm "
                                f"(stored: {_objects(subtasks)}); annotate it again")
        arms = cut_arms(ep, subtasks, constraints)
        sources.append(SourceDemo(str(ep.path), tuple(seg for segs in arms.segments for seg in segs), arms))
    objects = {tuple(seg.object for seg in s.segments) for s in sources}
    if len(objects) > 1:
        raise GenerateError(f"sources are annotated with different subtasks: {sorted(objects)}")
    ((scene, robot, hz),) = kinds
    refs = tuple(arm_refs(constraints, sources[0].arms.arms)) if two_arm else ()
    job = Job(scene=scene, robot=robot, control_hz=hz, sources=tuple(sources), formats=("mcap",), keep_failures=False,
              task_file=episodes[0].meta.extra.get(TASK_FILE_KEY), constraints=refs)
    return job, sources


def _task_of(ep):
    """The task an episode recorded (its embedded task file, else by name), None when there is none."""
    try:
        return task_for_episode(ep.meta.scene, ep.meta.extra)
    except TeleopError:
        return None


def _objects(subtasks) -> str:
    """"cube, bin", or per arm "left: cube, world; right: cube"."""
    groups: dict[str, list[str]] = {}
    for s in subtasks:
        groups.setdefault(s.arm, []).append(s.object)
    return "; ".join(f"{arm}: " * bool(arm) + ", ".join(objs) for arm, objs in groups.items())


# -- the worker -----------------------------------------------------------------


def run_attempt(job: Job, seed: int, index: int, workdir: Path) -> Attempt:
    """Generate, record and check one seed; the episode's bytes come back if it is kept."""
    try:
        session = job.session(seed)
    except PlacementError as exc:  # this seed only; any other task-file error is the run's, and stops it
        return Attempt(seed, index, False, 0, (), error=first_line(exc), reason=PLACEMENT)
    rng = np.random.default_rng([seed, 0x6E6])  # which source serves each subtask, among the nearest
    two_arm = job.sources[0].arms
    if two_arm is None:
        n_subtasks = len(job.sources[0].segments)
        chosen = choose_segments(session, [[src.segments[i] for src in job.sources] for i in range(n_subtasks)], rng)
        device: PlanDevice | ArmsPlanDevice = PlanDevice(session, chosen, settle_s=job.settle_s)
        per_arm: dict = {}
    else:
        by_arm = choose_arm_segments(session, [src.arms for src in job.sources], job.constraints, rng, job.source_per_arm)
        chosen = [seg for segs in by_arm for seg in segs]
        device = ArmsPlanDevice(session, by_arm, job.constraints, settle_s=job.settle_s)
        per_arm = {"arms": {arm: {"subtasks": [seg.object for seg in segs], "sources": [seg.source for seg in segs]}
                            for arm, segs in zip(two_arm.arms, by_arm)},
                   "constraints": [{"kind": kind, "subtasks": [[two_arm.arms[k], i] for k, i in refs]}
                                   for kind, refs in job.constraints],
                   "source_per_arm": job.source_per_arm}
    names = tuple(dict.fromkeys(seg.source for seg in chosen))
    provenance = {
        "source_episodes": names,
        "generator": {"name": GENERATOR, "version": GENERATOR_VERSION, "seed": seed,
                      "subtasks": [seg.object for seg in chosen], "sources": [seg.source for seg in chosen],
                      "settle_s": job.settle_s, **per_arm},
    }
    out = workdir / f"seed{seed}"
    recorder = Recorder(session, out, formats=job.formats, verify="sync", source="generated", provenance=provenance)
    recorder.next_index = index
    with recorder:
        result = run_episode(session, [device], max_steps=job.max_steps)
    attempt = Attempt(seed, index, result.success, result.steps, names, bit_exact=result.replay_bit_exact,
                      reason="" if result.success else TASK_NOT_DONE)
    if result.success or job.keep_failures:
        attempt.files = [(p.name, p.read_bytes()) for p in recorder.paths]
        if two_arm is not None and result.steps > 0:  # annotated per arm as generated: where each subtask began
            subtasks = generated_subtasks(device, two_arm.arms, result.steps)  # type: ignore[arg-type]
            for p in recorder.paths:
                try:
                    side = write_subtasks(p, subtasks, result.steps, by="generator")
                except AnnotationError:  # an arm that never began a subtask: the episode stays, unannotated
                    break
                attempt.files.append((side.name, side.read_bytes()))
    shutil.rmtree(out, ignore_errors=True)
    return attempt


def run_batch(job: Job, seeds: Sequence[tuple[int, int]]) -> list[Attempt]:
    """Attempts for (seed, index) pairs, in order; the unit of work a worker or Ray task takes."""
    with scratch_dir() as tmp:  # a killed worker's is swept by the next run's first batch
        return [run_attempt(job, seed, index, tmp) for seed, index in seeds]


def _warm_up(job: Job) -> None:
    """A local worker's start: imports and a first build of the scene, paid before the clock starts."""
    job.session(0)


# -- the driver -----------------------------------------------------------------


@dataclass
class GenerateOptions:
    out: Path
    num: int
    seed: int = 0
    workers: int | None = None  # None: the number of cores
    ray: str | None = None  # "auto" or an address: run on Ray instead of local processes
    keep_failures: bool = False
    formats: tuple[str, ...] = ("mcap",)
    max_attempts: int | None = None  # None: 10 x num + 10
    batch: int | None = None  # seeds per task; None: a few per worker, for balance
    progress: bool = True
    force_new: bool = False  # start a new run in an --out that holds another run's (or other) episodes
    force: bool = False  # go on when the free space looks too small for the episodes asked
    variation: Variation | None = None  # `--vary physics`: each seed's physics drawn into its scene, recorded
    source_per_arm: bool = False  # `--source-per-arm`: a two-arm task's arms choose their sources each on its own


def generate(sources: Iterable[str | Path], opts: GenerateOptions,
             log: Callable[[str], None] | None = None, cancel: threading.Event | None = None) -> GenerateSummary:
    """Generate `opts.num` successful episodes from the sources into `opts.out`, in total.

    A re-run with the same sources and options continues where the last one stopped
    (teleop.generate.resume): the seeds already kept or failed there are skipped and
    only the missing episodes are generated. Other work in `opts.out` is refused
    (ResumeRefused) unless `opts.force_new`.
    cancel: a token (the CLI sets it on Ctrl-C); once set, generation stops as on a
    KeyboardInterrupt: the batches in flight end, what was kept stays, `interrupted` is true.
    A file that cannot be written (a full disk) stops it: the workers end, the episodes
    kept stay whole, and a WriteError is raised with the summary as its `summary`.
    """
    log = log or (lambda line: print(line, file=sys.stderr))
    if opts.num <= 0:
        raise GenerateError(f"the number of episodes to generate must be positive, got {opts.num}")
    if opts.workers is not None and opts.workers <= 0:
        raise GenerateError(f"workers must be positive, got {opts.workers}")
    unknown = [f for f in opts.formats if f not in FORMATS]
    if unknown or not opts.formats:
        raise GenerateError(f"format {','.join(unknown) or '(none)'}: choose mcap, hdf5 or both")
    sweep_stale()  # batch folders that killed workers on this host left (their first batches sweep other hosts)
    if opts.out.exists() and not opts.out.is_dir():
        raise GenerateError(f"{opts.out} exists and is not a directory")
    if opts.ray is not None:  # before any work: a bad address is the only thing said
        connect_ray(opts.ray)
    stub, sources = load_sources(sources, log)
    job = Job(stub.scene, stub.robot, stub.control_hz, tuple(sources), tuple(opts.formats), opts.keep_failures,
              task_file=stub.task_file, variation=opts.variation, constraints=stub.constraints,
              source_per_arm=opts.source_per_arm)
    try:  # a task file or a --vary range the task cannot take answers now, in one line, not in every worker
        job.session(opts.seed)
    except PlacementError:
        pass  # that seed alone: a failure (reason "placement") when its turn comes
    max_attempts = opts.max_attempts or 10 * opts.num + 10
    try:
        identity = run_identity(sources, opts.seed, opts.formats, opts.keep_failures, GENERATOR_VERSION)
        if opts.variation is not None and opts.variation.physics:  # only then: journals from before stay resumable
            identity["variation"] = {k: v for k, v in opts.variation.to_json().items() if k in ("kinds", "overrides", "split")}
        if opts.source_per_arm and sources[0].arms is not None:  # only then: other journals stay resumable
            identity["source_per_arm"] = True
        journal = Journal(opts.out, identity, force_new=opts.force_new, log=log)
    except WriteError as exc:
        exc.summary = GenerateSummary()  # type: ignore[attr-defined]
        raise
    done = journal.done
    summary = GenerateSummary(resumed_from=len(done.kept), seeds_skipped=sorted(done.seeds))
    if summary.resumed_from >= opts.num:  # nothing left to do: no workers started
        return summary
    t_start = time.perf_counter()
    if opts.ray is not None:
        runner = Runner(ray=opts.ray, shared=job, cancel=cancel)
    else:
        workers = opts.workers or os.cpu_count() or 1
        runner = Runner(workers, shared=job, setup=_warm_up, setup_args=(job,), cancel=cancel, preload=(__name__,))
    summary.workers, summary.backend = runner.workers, runner.backend
    work = 0.0
    try:
        with runner:
            summary.startup_s = runner.wait_started()  # workers' start, imports, a first build (or joining Ray): not timed as work
            # Small batches locally (progress and Ctrl-C stay prompt); larger on Ray, where a task costs more to send.
            batch = opts.batch or (max(1, min(8, opts.num // (2 * runner.workers))) if runner.backend == "ray" else 2)
            t0 = time.perf_counter()
            try:
                _drive(runner, opts, journal, batch, max_attempts, summary)
            except KeyboardInterrupt:
                summary.interrupted = True
                runner.stop()  # the batches in flight end now rather than finish: what was kept stays
            finally:
                work = time.perf_counter() - t0
    except WriteError as exc:  # the runner has stopped its workers: the episodes kept are whole
        summary.error = str(exc)
        exc.summary = summary  # type: ignore[attr-defined]
        raise
    finally:
        summary.seconds = round(time.perf_counter() - t_start, 3)
        summary.success_rate = round(summary.successes / summary.attempts, 4) if summary.attempts else 0.0
        summary.episodes_per_min = round(60.0 * summary.successes / work, 2) if work > 0 else 0.0
    if summary.placement_error:  # a defect of the task file, not of generation: said once, with the file's line
        log(f"{summary.failures[PLACEMENT]} seeds could not be placed (first: {summary.placement_error})")
    kept = summary.resumed_from + summary.successes
    if kept < opts.num and not summary.interrupted:
        summary.stopped_early = (f"stopped after {summary.attempts} attempts (the bound) with "
                                 f"{kept} of {opts.num} episodes")
    return summary


def _seed_offsets(done: Done, seed: int) -> Iterator[int]:
    """Offsets i of the seeds seed+i still to attempt, in order: the ones --out already holds are skipped."""
    skip = done.seeds
    return (i for i in itertools.count() if seed + i not in skip)


def _drive(runner: Runner, opts: GenerateOptions, journal: Journal, batch: int, max_attempts: int,
           summary: GenerateSummary) -> None:
    """Hand out batches of seeds as they are needed and take their attempts in seed order."""
    base = journal.done.base
    offsets = _seed_offsets(journal.done, opts.seed)
    need = opts.num - summary.resumed_from
    handed = 0  # attempts handed out
    in_flight = 2 * runner.workers
    columns = (TextColumn("generate"), BarColumn(), MofNCompleteColumn(), TextColumn("kept · {task.fields[info]}"),
               TimeRemainingColumn())
    with Progress(*columns, disable=not opts.progress, transient=False,
                  console=Console(stderr=True)) as bar:
        task = bar.add_task("generate", total=opts.num, info="", completed=summary.resumed_from)
        while summary.successes < need:
            while runner.running < in_flight and handed < max_attempts:
                # Hand out only the attempts still expected to be needed: near the end, work beyond
                # --num successes would be thrown away (the rate is estimated from the attempts so far).
                rate = (summary.successes + 1) / (summary.attempts + 1)
                deficit = math.ceil((need - summary.successes) / rate) - (handed - summary.attempts)
                if deficit <= 0:
                    break
                size = max(1, min(batch, math.ceil(deficit / runner.workers), max_attempts - handed))
                chosen = [next(offsets) for _ in range(size)]
                runner.submit(run_batch, runner.shared, [(opts.seed + i, base + i) for i in chosen])
                handed += size
            if not runner.pending:
                break
            runner.wait()
            for attempts in runner.ready():
                for attempt in attempts:
                    if summary.successes >= need:
                        break
                    _take(attempt, opts, journal, summary)
                if summary.successes >= need:
                    break
            rate = summary.successes / summary.attempts if summary.attempts else 0.0
            bar.update(task, completed=summary.resumed_from + summary.successes,
                       info=f"{summary.attempts} attempts, {rate:.0%} success")


def _take(attempt: Attempt, opts: GenerateOptions, journal: Journal, summary: GenerateSummary) -> None:
    """Count one attempt in seed order, write what is kept, then journal it."""
    directory = opts.out if attempt.success else opts.out / "failures"  # failures: success false inside, kept apart
    written = []
    if attempt.files:
        try:
            directory.mkdir(parents=True, exist_ok=True)
            for name, data in attempt.files:
                # NAME.part, then a rename: a killed run or a full disk never leaves a half file under an episode's name
                written.append(write_bytes_whole(directory / name, data))
        except OSError as exc:
            for path in written:  # one format of two is not an episode (a re-run makes both again)
                path.unlink(missing_ok=True)
            raise write_error(directory, exc) from None
    summary.attempts += 1
    if attempt.bit_exact is False:
        summary.not_bit_exact += 1
    if attempt.success:
        summary.successes += 1
        summary.seeds.append(attempt.seed)
    else:
        summary.failures_kept += bool(attempt.files)
        summary.failures[attempt.reason] = summary.failures.get(attempt.reason, 0) + 1
        if attempt.reason == PLACEMENT and not summary.placement_error:
            summary.placement_error = f"seed {attempt.seed}: {attempt.error}"
    summary.files.extend(str(p) for p in written if not p.name.endswith(SIDECAR_SUFFIX))  # episodes, not their subtasks
    journal.record(attempt.seed, attempt.success, written, reason=attempt.reason, error=attempt.error)
    if attempt.success and summary.successes == 1 and not opts.force:
        _check_space(opts, sum(len(data) for _, data in attempt.files), opts.num - summary.resumed_from - 1)


def _check_space(opts: GenerateOptions, per_episode: int, more: int) -> None:
    """After the first kept episode: stop when the rest clearly will not fit (NotEnoughSpace, one line)."""
    if more > 0:
        check_free_space(opts.out, per_episode * more, f"{more} more episodes of ~{per_episode / 1000:.0f} KB")


__all__ = ["GenerateError", "GenerateOptions", "GenerateSummary", "NotEnoughSpace", "generate", "load_sources",
           "run_batch"]
