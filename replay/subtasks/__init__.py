"""Subtasks: where an episode's object-centric subtasks begin and end, found, edited and stored.

- sidecar.py: the stored form, a `.subtasks.json` file beside the episode (`Subtask`,
  `read_subtasks`, `write_subtasks`); the recording itself is never rewritten.
- annotate.py: boundaries found from what the episode recorded (gripper events and contacts),
  `annotate` for the `teleop annotate` command, and how far a rollout got (`progress_of`).
- edit.py: hand edits that keep the subtasks contiguous (the replay viewer's Subtasks panel,
  teleop/web/replay_page/subtasks.py, is the page over it).

Nothing is re-exported here: replay/episode.py reads the sidecar, and annotate.py reads episodes,
so importing the modules by name keeps the two from running into each other.
"""
