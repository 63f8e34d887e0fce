"""Tasks: the task base, task files (read, placed, built, judged, bundled), success expressions and the registry."""
