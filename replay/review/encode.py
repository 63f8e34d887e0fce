"""Writing RGB frames to an MP4 (H.264) or a GIF through PyAV.

The MP4 is what browsers play: H.264 in yuv420p (so even width and height),
with its index at the front (faststart) so a page can start playing before the
whole file has arrived. The file is written under a `.part` name and renamed
when finished, so a crash or a full disk never leaves a half video at `out`.
"""

from __future__ import annotations

import os
from fractions import Fraction
from pathlib import Path

import numpy as np

from scenes.errors import TeleopError

FORMATS = {".mp4": "mp4", ".gif": "gif"}
PART = ".part"


class VideoError(TeleopError, ValueError):
    """A video that cannot be written (no PyAV, a bad path, a full disk); the message is one line."""


def video_format(out: str | Path) -> str:
    """'mp4' or 'gif' from the file name; anything else is a VideoError."""
    fmt = FORMATS.get(Path(out).suffix.lower())
    if fmt is None:
        raise VideoError(f"{out}: the video must end in .mp4 or .gif")
    return fmt


def check_writable(out: str | Path) -> Path:
    """Fail now (before any rendering) if `out` cannot be written: a missing or read-only folder."""
    out = Path(out)
    video_format(out)
    folder = out.parent if str(out.parent) else Path(".")
    if not folder.is_dir():
        raise VideoError(f"{out}: no such folder {folder}")
    if out.is_dir():
        raise VideoError(f"{out}: is a folder")
    if not os.access(folder, os.W_OK):
        raise VideoError(f"{out}: cannot write in {folder} (permission denied)")
    return out


def _av():
    try:
        import av
    except ImportError:
        raise VideoError("writing videos needs PyAV: pip install av") from None
    return av


def _disk_error(out: Path, exc: OSError) -> VideoError:
    """'<out>: cannot write: No space left on device' (the OS's words; PyAV raises OSErrors with an errno)."""
    why = os.strerror(exc.errno) if isinstance(exc.errno, int) and exc.errno > 0 else (exc.strerror or str(exc))
    return VideoError(f"{out}: cannot write: {why}")


class VideoWriter:
    """Frames in (H, W, 3) uint8, all of one size, out to an MP4 or GIF at `fps` frames per second."""

    def __init__(self, out: str | Path, fps: float, crf: int = 23) -> None:
        self.out = check_writable(out)
        self.format = video_format(self.out)
        self.fps = Fraction(fps).limit_denominator(1001)
        if self.fps <= 0:
            raise VideoError(f"--fps {fps}: must be positive")
        self.crf = crf
        self.part = self.out.with_name(self.out.name + PART)
        self.frames = 0
        self.width = self.height = 0  # px, as encoded (even for H.264)
        self._container = None
        self._stream = None
        self._av = _av()

    def _open(self, height: int, width: int) -> None:
        av = self._av
        try:
            if self.format == "mp4":
                self._container = av.open(str(self.part), "w", format="mp4", options={"movflags": "+faststart"})
                stream = self._container.add_stream("libx264", rate=self.fps)
                stream.pix_fmt = "yuv420p"
                stream.options = {"crf": str(self.crf), "preset": "ultrafast"}  # 2.4x veryfast's speed, 2.8x its size
            else:
                self._container = av.open(str(self.part), "w", format="gif")
                stream = self._container.add_stream("gif", rate=self.fps)
                stream.pix_fmt = "rgb8"
            stream.width, stream.height = width + width % 2, height + height % 2
            self.width, self.height = stream.width, stream.height
            stream.codec_context.time_base = 1 / self.fps
        except OSError as exc:
            self._drop()
            raise _disk_error(self.out, exc) from None
        self._stream = stream

    def write(self, frame: np.ndarray) -> None:
        """Add one frame (padded to even sizes for H.264 by repeating the last row or column)."""
        if self._stream is None:
            self._open(frame.shape[0], frame.shape[1])
        stream = self._stream
        if frame.shape[0] != stream.height or frame.shape[1] != stream.width:
            frame = np.pad(frame, ((0, stream.height - frame.shape[0]), (0, stream.width - frame.shape[1]), (0, 0)),
                           mode="edge")
        video_frame = self._av.VideoFrame.from_ndarray(np.ascontiguousarray(frame), format="rgb24")
        video_frame.pts = self.frames
        self.frames += 1
        self._mux(stream.encode(video_frame))

    def _mux(self, packets) -> None:
        try:
            self._container.mux(packets)
        except OSError as exc:
            self._drop()
            raise _disk_error(self.out, exc) from None

    def close(self) -> Path:
        """Finish the file and move it to `out` (nothing is written for zero frames: a VideoError)."""
        if self._stream is None:
            raise VideoError(f"{self.out}: no frames to write")
        self._mux(self._stream.encode(None))
        try:
            self._container.close()
            self._container = None
            os.replace(self.part, self.out)
        except OSError as exc:
            self._drop()
            raise _disk_error(self.out, exc) from None
        return self.out

    def _drop(self) -> None:
        """Forget a video that failed: close what is open and remove the part file."""
        container, self._container = self._container, None
        if container is not None:
            try:
                container.close()
            except Exception:  # noqa: BLE001 - the first error is the one to report
                pass
        try:
            self.part.unlink()
        except OSError:
            pass

    def abort(self) -> None:
        self._drop()
