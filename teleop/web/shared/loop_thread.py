"""The one lifecycle the web session's background loops share: a daemon thread, stopped by an Event."""

from __future__ import annotations

import threading


class LoopThread:
    """Runs `self._run` on a daemon thread; `_run` returns once `self._stop` is set."""

    join_timeout = 2.0  # s that stop() waits for the loop to notice

    def _init_thread(self, name: str) -> None:
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)

    def _run(self) -> None:
        raise NotImplementedError

    def start(self) -> None:
        self._thread.start()

    def stop(self, timeout: float | None = None) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(self.join_timeout if timeout is None else timeout)
