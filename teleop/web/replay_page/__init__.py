"""The replay viewer (`teleop replay EP --serve`): viewer (scrub, play, camera) and subtasks (the
Subtasks panel over replay/subtasks/)."""
