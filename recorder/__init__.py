"""Recording demonstrations: one episode per file, MCAP (live, Foxglove) and/or HDF5 (robomimic).

The control thread fills the writer's next preallocated row in place
(`EpisodeWriter.claim` / `commit`), or hands it a `StepRecord` (`append`); a
writer thread encodes and flushes every 0.1 s. The file layout is
documented in `recorder.format`, which readers share.
"""

from recorder.step import StepRecord
from recorder.writer import FORMATS, EpisodeWriter, RecorderError, episode_path, next_episode_index

__all__ = [
    "FORMATS",
    "EpisodeWriter",
    "RecorderError",
    "StepRecord",
    "episode_path",
    "next_episode_index",
]
