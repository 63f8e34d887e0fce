"""A reviewer's verdict on an episode, kept in a sidecar beside it: `<episode>.review.json`.

The episode file itself is never rewritten. Each write replaces the whole sidecar
atomically (recorder.disk's `write_text_whole`: a temporary file of the writer's own,
renamed over it), so two reviewers writing at once leave one complete verdict: the
last one written, with its reviewer named.
"""

from __future__ import annotations

import json
from datetime import datetime, timezone
from pathlib import Path

from recorder.disk import write_text_whole
from scenes.errors import TeleopError

SUFFIX = ".review.json"
VERDICTS = ("accept", "reject")


class VerdictError(TeleopError, ValueError):
    """A verdict that is not accept or reject, or no reviewer named; one line."""


def verdict_path(episode: str | Path) -> Path:
    """The sidecar of an episode file: its name plus SUFFIX."""
    episode = Path(episode)
    return episode.with_name(episode.name + SUFFIX)


def read_verdict(episode: str | Path) -> dict | None:
    """`{"verdict", "reviewer", "time", "note"}` of an episode, or None (never reviewed, or an unreadable sidecar)."""
    try:
        doc = json.loads(verdict_path(episode).read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(doc, dict) or doc.get("verdict") not in (*VERDICTS, None):
        return None
    return {"verdict": doc.get("verdict"), "reviewer": str(doc.get("reviewer", "")), "time": str(doc.get("time", "")),
            "note": str(doc.get("note", ""))}


def write_verdict(episode: str | Path, verdict: str | None, reviewer: str, note: str = "") -> dict:
    """Record a verdict (None: a note alone, the verdict left unset) and return what was written."""
    if verdict not in (*VERDICTS, None):
        raise VerdictError(f"verdict {verdict!r}: must be one of {', '.join(VERDICTS)}")
    reviewer = str(reviewer or "").strip()
    if not reviewer:
        raise VerdictError("a verdict needs the reviewer's name")
    episode = Path(episode)
    doc = {"episode": episode.name, "verdict": verdict, "reviewer": reviewer,
           "time": datetime.now(timezone.utc).isoformat(timespec="seconds"), "note": str(note or "")}
    write_text_whole(verdict_path(episode), json.dumps(doc, indent=1) + "\n", shared=True)  # a WriteError if it cannot
    return {k: doc[k] for k in ("verdict", "reviewer", "time", "note")}
