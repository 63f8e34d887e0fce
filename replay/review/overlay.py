"""The strip drawn under each video frame: what the episode is doing at that step.

Two lines of text and a bar, `STRIP_HEIGHT` pixels tall, as wide as the frame:
the task's instruction and the time; the subtask in progress, who drives and a
success badge (grey until the task's success test holds, then `SUCCESS_RGB`);
and a bar with one segment per subtask, a white tick at each boundary and a
cursor at the current step. Text is drawn with Pillow when it is installed (the
bar and the badge need nothing but numpy). Strips are cached by what changes
between them, so a frame costs one copy and the time's text.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

STRIP_HEIGHT = 40  # px
BACKGROUND = (24, 24, 28)
TEXT_RGB = (235, 235, 235)
SUCCESS_RGB = (40, 190, 80)  # the badge once the task succeeds
PENDING_RGB = (90, 90, 96)  # the badge before
SEGMENT_RGB = ((70, 110, 200), (200, 140, 60))  # subtasks alternate these on the bar
BAR_RGB = (60, 60, 66)  # the bar with no subtasks
BADGE_WIDTH = 64  # px


@dataclass(frozen=True)
class StepInfo:
    """What the strip shows at one control step."""

    step: int
    seconds: float  # time since the episode's start, s
    subtask: int | None  # index into `Timeline.subtasks`, None without annotations
    driver: str  # "operator (gizmo)", "policy", "generated", "script"
    success: bool  # the task's success test holds at this step


@dataclass(frozen=True)
class Timeline:
    """What stays the same over an episode: its instruction, length and subtasks."""

    instruction: str
    steps: int
    total_seconds: float
    subtasks: Sequence[tuple[str, int, int]] = ()  # (object, start step, end step + 1)


def _font(size: int):
    try:
        from PIL import ImageFont
    except ImportError:
        return None
    try:
        return ImageFont.load_default(size=size)
    except (TypeError, OSError, ImportError):  # Pillow < 10.1 or no FreeType: the bitmap font
        return ImageFont.load_default()


def draw_text(image: np.ndarray, xy: tuple[int, int], text: str, font, rgb=TEXT_RGB) -> None:
    """Write `text` into `image` (H, W, 3 uint8) in place; nothing without Pillow."""
    if font is None or not text:
        return
    from PIL import Image, ImageDraw

    pil = Image.fromarray(image)
    ImageDraw.Draw(pil).text(xy, text, fill=rgb, font=font)
    image[...] = np.asarray(pil)


class Overlay:
    """Draws the strip for frames `width` pixels wide."""

    def __init__(self, timeline: Timeline, width: int) -> None:
        self.timeline = timeline
        self.width = int(width)
        self.font = _font(12)
        self._cache: dict[tuple, np.ndarray] = {}
        self._glyphs: dict[str, np.ndarray] = {}
        self._bar = self._draw_bar()

    def _bar_x(self, step: float) -> int:
        return int(round(step / max(1, self.timeline.steps) * (self.width - 1)))

    def _draw_bar(self) -> np.ndarray:
        bar = np.empty((6, self.width, 3), np.uint8)
        bar[:] = BAR_RGB
        for i, (_, start, end) in enumerate(self.timeline.subtasks):
            bar[:, self._bar_x(start):max(self._bar_x(end), self._bar_x(start) + 1)] = SEGMENT_RGB[i % 2]
        for _, start, _ in list(self.timeline.subtasks)[1:]:
            bar[:, max(0, self._bar_x(start) - 1):self._bar_x(start) + 1] = 255  # a tick at each boundary
        return bar

    def _base(self, info: StepInfo) -> np.ndarray:
        key = (info.subtask, info.driver, info.success)
        strip = self._cache.get(key)
        if strip is None:
            strip = np.empty((STRIP_HEIGHT, self.width, 3), np.uint8)
            strip[:] = BACKGROUND
            subtasks = self.timeline.subtasks
            where = (f"subtask {info.subtask + 1}/{len(subtasks)}: {subtasks[info.subtask][0]}"
                     if info.subtask is not None and subtasks else "no subtasks")
            draw_text(strip, (4, 1), self.timeline.instruction, self.font)
            draw_text(strip, (4, 16), f"{where} · {info.driver}", self.font)
            badge = strip[15:31, self.width - BADGE_WIDTH - 2:self.width - 2]
            badge[:] = SUCCESS_RGB if info.success else PENDING_RGB
            draw_text(badge, (4, 1), "success" if info.success else "not yet", self.font)
            strip[STRIP_HEIGHT - 7:STRIP_HEIGHT - 1] = self._bar
            self._cache[key] = strip
        return strip

    def _label(self, text: str) -> np.ndarray:
        """`text` as a (15, w, 3) image from glyphs drawn once each (Pillow per frame costs ~2 ms)."""
        parts = []
        for char in text:
            glyph = self._glyphs.get(char)
            if glyph is None:
                width = max(1, int(np.ceil(self.font.getlength(char)))) if self.font is not None else 6
                glyph = np.empty((15, width, 3), np.uint8)
                glyph[:] = BACKGROUND
                draw_text(glyph, (0, 1), char, self.font)
                self._glyphs[char] = glyph
            parts.append(glyph)
        return np.concatenate(parts, axis=1)

    def strip(self, info: StepInfo) -> np.ndarray:
        """The (STRIP_HEIGHT, width, 3) strip for one step."""
        strip = self._base(info).copy()
        label = self._label(f"{info.seconds:.2f} / {self.timeline.total_seconds:.2f} s")
        corner = strip[0:15, max(0, self.width - 110):]
        corner[:] = BACKGROUND  # over the end of a long instruction
        width = min(label.shape[1], corner.shape[1] - 2)
        corner[:, 2:2 + width] = label[:, :width]
        x = self._bar_x(info.step)
        strip[STRIP_HEIGHT - 9:STRIP_HEIGHT, max(0, x - 1):x + 2] = (255, 230, 0)  # the cursor
        return strip
