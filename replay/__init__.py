"""Reading and replaying recorded episodes (MCAP or HDF5; layout in recorder.format).

State mode (`replay_states`) restores each recorded state for viewing and
rendering; action mode (`resimulate`) restores the first state and re-steps the
recorded ctrl, verifying every state bit for bit.
"""

from replay.engine import VerifyResult, compat_warnings, replay_states, resimulate, state_poses, verify_file
from replay.episode import Episode, EpisodeError, find_episodes, load_episode

__all__ = [
    "Episode",
    "EpisodeError",
    "VerifyResult",
    "compat_warnings",
    "find_episodes",
    "load_episode",
    "replay_states",
    "resimulate",
    "state_poses",
    "verify_file",
]
