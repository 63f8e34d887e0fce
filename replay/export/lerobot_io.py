"""LeRobot as an optional extra, for the one-process export (serial.py) and the sharded one (shards.py).

Here so that both import it and neither takes the other's private helpers: the
import with a one-line error naming the extra to install, that error, and the
size on disk of what LeRobot wrote.
"""

from __future__ import annotations

import logging

from pathlib import Path

from replay.errors import TeleopError

LEROBOT_HINT = "LeRobot is not installed: pip install 'mujoco-teleop[lerobot]'"


class ExportError(TeleopError, ValueError):
    """Bad export input (files, flags, an existing dataset); the message is one line."""


def load_lerobot():
    """The LeRobotDataset class (imported here: seconds), or a one-line ExportError saying which extra to install."""
    try:
        from lerobot.datasets import LeRobotDataset
    except ImportError:
        raise ExportError(LEROBOT_HINT) from None
    try:
        import av

        # LeRobot's encoder hands logging back to FFmpeg's own printer: keep it to errors,
        # not an "[mp4 @ 0x...] Starting second pass" line per video.
        av.logging.set_libav_level(av.logging.ERROR)
    except (ImportError, AttributeError):
        pass
    # A full disk reaches the export as the encoder's error, said in one line; LeRobot's own log of it
    # ("Encoder thread error: [Errno 28] ...") would be a second one (from each worker, in parallel).
    logging.getLogger("lerobot.datasets.video_utils").setLevel(logging.CRITICAL)
    return LeRobotDataset


def dir_size(path: Path) -> int:
    """Bytes in the files under `path` (a dataset folder)."""
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file())
