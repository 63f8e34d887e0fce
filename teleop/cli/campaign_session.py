"""One operator's session process of `teleop campaign` (started by the lobby, not by hand).

`python -m teleop.cli.campaign_session` reads its SessionSpec as one JSON line on
stdin, then serves the session as `teleop serve` does (the page's inputs only: the
operator is at another machine) on a port the system picks (reported in its status file,
SessionStatus) with its own token, never written to its log, recording into
out/<task>/ with the campaign's seeds and provenance. It keeps stdin open as its
lifeline: when the lobby goes away, however it ends (kill -9 included), stdin reaches
end of file and the session stops as on Ctrl-C (an episode in progress is saved,
marked incomplete). It also stops after the spec's minutes, and on SIGINT / SIGTERM.
"""

from __future__ import annotations

import gc
import json
import sys
import threading
from pathlib import Path

from devices.registry import BROWSER_DEVICES
from scenes.errors import TeleopError, first_line
from scenes.vary.variation import Variation, parse_vary
from teleop.campaign.ledger import next_episode_index, next_seed
from teleop.campaign.operator_session import CampaignSession, SessionSpec, SessionStatus
from teleop.campaign.progress import Progress
from teleop.cli.signals import cancel_on_interrupt
from teleop.control.recording import Recorder
from teleop.control.session_setup import open_session_devices

DEVICES = ("gizmo", *BROWSER_DEVICES)  # what a remote operator's browser can drive; keys come by the page
LOBBY_STATUS_PERIOD_S = 0.5  # s between a campaign session's status writes: the lobby's admin page and /api/status read them


def read_spec() -> SessionSpec:
    line = sys.stdin.readline()
    if not line:
        raise SystemExit("campaign session: no spec on stdin (this process is started by `teleop campaign`)")
    return SessionSpec(**json.loads(line))


def watch_lifeline(stop: threading.Event) -> None:
    """Set `stop` when stdin closes (the lobby ended or ended this session)."""
    def run() -> None:
        try:
            while sys.stdin.readline():
                pass
        except (OSError, ValueError):
            pass
        stop.set()

    threading.Thread(target=run, name="campaign-lifeline", daemon=True).start()


def run(spec: SessionSpec, stop: threading.Event) -> int:
    from replay.render import rasterize_in_render_threads
    from teleop.web.session_page.serve import serve  # viser: imported once the spec is read
    from teleop.web.session_page.serve_options import ServeOptions

    rasterize_in_render_threads()  # the page's camera picture renders in a thread of its own: no llvmpipe threads

    kinds = parse_vary(spec.vary, "generation")
    variation = Variation(kinds=kinds) if kinds else None
    out = Path(spec.out)
    progress: Progress | None = None
    session = CampaignSession(spec.task, lambda task: next_seed(out, task), lambda task: next_episode_index(out, task),
                              lambda task: progress.next_task(task) if progress is not None else None,
                              scene=spec.scene, robot=spec.robot, control_hz=spec.control_hz, variation=variation)
    progress = Progress(spec, lambda: session.campaign_task)
    formats = ("mcap", "hdf5") if spec.format == "both" else (spec.format,)
    Recorder(session, spec.record_dir, formats, verify="background", on_error="stop", provenance=spec.provenance)
    devices, problems = open_session_devices(",".join(DEVICES), session.controller.n_arms, 0.15, 0.8, serving=True,
                                             log=lambda line: print(line, flush=True))
    timer = threading.Timer(spec.minutes * 60.0, stop.set)
    timer.daemon = True
    timer.start()
    progress.start()
    # This process is the session's alone: what exists now (modules, the scene, the recorder) lives as long as it,
    # so the garbage collector's full passes need not walk it again (~150,000 objects).
    gc.collect()
    gc.freeze()
    try:
        options = ServeOptions(host=spec.host, port=spec.port, token=spec.token, page_keyboard=True,
                               status_file=Path(spec.status_file), status_period_s=LOBBY_STATUS_PERIOD_S,
                               status_form=lambda st: SessionStatus.from_serve(st).to_json(), headline=progress.line,
                               draw_unwatched=False, print_token=False)  # its output is a log file: the lobby hands out the URL
        return serve(session, options, devices=devices, problems=problems, stop=stop, log=lambda line: print(line, flush=True))
    finally:
        timer.cancel()
        progress.stop()


def main() -> int:
    spec = read_spec()
    with cancel_on_interrupt(even_if_ignored=True) as stop:
        watch_lifeline(stop)
        try:
            return run(spec, stop)
        except TeleopError as exc:
            print(f"campaign session {spec.session}: error: {first_line(exc)}", file=sys.stderr, flush=True)
            return 2


if __name__ == "__main__":
    sys.exit(main())
