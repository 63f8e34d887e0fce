"""A reviewer's verdict on an episode, kept in a sidecar beside it: `<episode>.review.json`.

The episode file itself is never rewritten. Each write replaces the whole sidecar
atomically (a temporary file renamed over it), so two reviewers writing at once
leave one complete verdict: the last one written, with its reviewer named.
"""

from __future__ import annotations

import json
import os
import tempfile
from datetime import datetime, timezone
from pathlib import Path

from recorder.disk import write_error
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


def write_whole(path: Path, text: str) -> None:
    """Replace `path` atomically through a temporary file of its own (one per writer, so writers
    in other processes never share one); a full disk or a read-only folder is a WriteError."""
    tmp = None
    try:
        with tempfile.NamedTemporaryFile("w", dir=path.parent, prefix=path.name + ".", suffix=".part",
                                         delete=False, encoding="utf-8") as fh:
            tmp = fh.name
            fh.write(text)
        os.replace(tmp, path)
    except OSError as exc:
        if tmp is not None:
            try:
                os.unlink(tmp)
            except OSError:
                pass
        raise write_error(path, exc) from None


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
    write_whole(verdict_path(episode), json.dumps(doc, indent=1) + "\n")
    return {k: doc[k] for k in ("verdict", "reviewer", "time", "note")}
