"""Read an MCAP file front to back, keeping every complete record even without a footer.

mcap's seeking reader needs the footer a killed writer never wrote; the linear
StreamReader gets everything up to the last whole chunk, which is what both the
episode reader and `teleop inspect --recover` want.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

from mcap.records import Footer, McapRecord
from mcap.stream_reader import StreamReader


@dataclass
class McapScan:
    """Outcome of a linear read: whether the file ended cleanly, and why not."""

    truncated: bool = False
    reason: str = ""
    records: int = 0
    footer: bool = field(default=False)


def iter_records(path: Path, scan: McapScan) -> Iterator[McapRecord]:
    """Yield records in file order; on a cut or corrupt tail, stop and note it in `scan`."""
    with open(path, "rb") as fh:
        reader = StreamReader(fh, validate_crcs=True)
        it = reader.records
        while True:
            try:
                record = next(it)
            except StopIteration:
                break
            except Exception as exc:  # noqa: BLE001 - any parse failure means the tail is unusable
                scan.truncated = True
                scan.reason = f"{type(exc).__name__}: {exc}".strip().rstrip(":") or type(exc).__name__
                break
            scan.records += 1
            if isinstance(record, Footer):
                scan.footer = True
            yield record
    if not scan.footer and not scan.truncated:
        scan.truncated, scan.reason = True, "no footer"
