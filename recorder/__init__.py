"""Recording demonstrations: one episode per file, MCAP (live, Foxglove) and/or HDF5 (robomimic).

The control thread fills the writer's next preallocated row in place
(`EpisodeWriter.claim` / `commit`), or hands it a `StepRecord` (`append`); a
writer thread encodes and flushes every 0.05 s. The file layout is
documented in `replay.schema`, which readers share. `recover_mcap` and
`convert_episode` rewrite files for `teleop inspect --recover` / `teleop convert`.
"""

from recorder.convert import convert_episode, recover_mcap, write_episode
from recorder.step import StepRecord
from recorder.writer import FORMATS, EpisodeWriter, RecorderError, episode_path, next_episode_index

__all__ = [
    "FORMATS",
    "EpisodeWriter",
    "RecorderError",
    "StepRecord",
    "convert_episode",
    "episode_path",
    "next_episode_index",
    "recover_mcap",
    "write_episode",
]
