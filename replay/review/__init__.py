"""Reviewing recorded episodes: videos rendered from their exact replay, quality flags, verdicts.

`video` renders and encodes (`teleop video`), `overlay` draws the strip under each
frame, `quality` computes each episode's flags and scores (its `THRESHOLDS`: every
limit, with its unit and why), `timebase` says how long a recorded step lasts and
moves a path to another rate, `verdicts` keeps a reviewer's verdict in a sidecar
beside the episode, and `listing` gathers the rows of the review page (`teleop
review`), cached beside the episodes.
"""
