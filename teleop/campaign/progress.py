"""The operator's progress line on their session page, and the next task when theirs is done.

"7 of 20 successful episodes of lift (yours: 3); the campaign: 213 of 500": counted from
the episode files (ledger.count_task) on a thread of its own every few seconds, so the
page's refresh only reads a string. When the session's task has all it wants, `next_task`
names the task that still wants the most among those this process can record (ties: file
order), and the line says so if there is none.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from pathlib import Path

from teleop.campaign.ledger import TaskCount, count_task
from teleop.campaign.operator_session import SessionSpec

REFRESH_S = 2.0


class Progress:
    """Keeps `line()` current for one session (start() it; stop() at the end); `current()` is its task now."""

    def __init__(self, spec: SessionSpec, current: Callable[[], str] | None = None) -> None:
        self.spec = spec
        self.current = current or (lambda: spec.task)
        self.wanted = {str(t[0]): int(t[1]) for t in spec.tasks} or {spec.task: spec.wanted}
        self._line = ""
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="campaign-progress", daemon=True)
        self.refresh()

    def counts(self, settle: bool = True) -> dict[str, TaskCount]:
        return {name: count_task(Path(self.spec.out), name, settle) for name in self.wanted}

    def refresh(self) -> None:
        counts, task = self.counts(), self.current()
        done, wanted = counts[task].successes, self.wanted[task]
        mine = counts[task].by_operator.get(self.spec.operator, [0, 0])[1]
        total = sum(min(counts[name].successes, n) for name, n in self.wanted.items())
        line = (f"**{done} of {wanted}** successful episodes of `{task}` (yours: {mine}); "
                f"the campaign: **{total} of {sum(self.wanted.values())}**")
        if done >= wanted:
            line += f"  \n**`{task}` has all its episodes: thank you!** Join again for the next task."
        self._line = line

    def line(self) -> str:
        return self._line

    def next_task(self, task: str) -> tuple[str, str] | None:
        """(folder, scene) of the task to record next when `task` has all it wants (None: stay on it)."""
        counts = self.counts(settle=False)  # the episode just saved counts
        if counts[task].successes < self.wanted[task]:
            return None
        best, left_best = None, 0
        for name, wanted, scene in self.spec.compatible():
            left = wanted - counts[name].successes if name in counts else 0
            if left > left_best:
                best, left_best = (name, scene), left
        return best

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()

    def _run(self) -> None:
        while not self._stop.wait(REFRESH_S):
            try:
                self.refresh()
            except OSError:  # the disk hiccuped: keep the last line
                pass
