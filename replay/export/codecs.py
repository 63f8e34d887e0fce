"""Video codecs: which encoder writes an export's videos, and which decoder LeRobot reads them back with.

LeRobot is an optional extra, imported only when an encoder is asked for.
"""

from __future__ import annotations

import re
from pathlib import Path

from replay.errors import first_line
from replay.export.lerobot_io import ExportError

# Video codecs, as LeRobot's RGBEncoderConfig settings. Measured on rendered 224x224 frames
# (GOP 2, as LeRobot sets): H.264 veryfast at CRF 20 gives AV1's PSNR (within 0.4 dB) at
# 1.1-1.2x its size, encodes in ~1 ms a frame instead of ~4.5 and decodes twice as fast when
# training reads it back. AV1 (LeRobot's own default) stays one flag away for the smallest files.
VIDEO_CODECS: dict[str, dict] = {
    "h264": {"vcodec": "h264", "preset": "veryfast", "crf": 20},
    "av1": {"vcodec": "libsvtav1"},
    "hevc": {"vcodec": "hevc", "preset": "veryfast", "crf": 24, "extra_options": {"x265-params": "log-level=error"}},
}

DEFAULT_CODEC = "h264"


def video_decoder() -> tuple[str, str]:
    """(decoder, why not torchcodec) for LeRobot reading the dataset back; why is "" for torchcodec.

    Asked once here and handed to LeRobot: left to itself, LeRobot retries importing torchcodec
    for each dataset it opens and, where FFmpeg's shared libraries are missing, logs ~100 lines
    of loading tracebacks before falling back to PyAV, which works.
    """
    import importlib.util

    if importlib.util.find_spec("torchcodec") is None:
        return "pyav", "torchcodec not installed"
    try:
        import torchcodec  # noqa: F401
    except (ImportError, OSError, RuntimeError) as exc:
        text = str(exc)
        if re.search(r"libav\w*\.so\S*: cannot open shared object file", text):
            return "pyav", "torchcodec unavailable: FFmpeg's shared libraries (versions 4-8) not found"
        return "pyav", f"torchcodec unavailable: {first_line(exc)[:120]}"
    return "torchcodec", ""


def new_encoder(settings: dict):
    """LeRobot's RGB encoder config, or a one-line ExportError when this PyAV cannot encode it."""
    from lerobot.configs.video import RGBEncoderConfig

    try:
        return RGBEncoderConfig(**settings)
    except (ValueError, ImportError) as exc:
        raise ExportError(f"video codec {settings['vcodec']}: {first_line(exc)}") from None


def dataset_encoder(meta, wanted: str | None, out: Path):
    """The encoder an existing dataset's videos were made with: appended episodes share its files."""
    from lerobot.configs.video import VIDEO_CODECS_ALIASES, encoder_config_from_video_info

    infos = [ft.get("info") or {} for ft in meta.features.values() if ft.get("dtype") == "video"]
    if not infos:
        return None
    stream = infos[0].get("video.codec")  # as the video stream names it: h264, hevc, av1
    encoder = VIDEO_CODECS_ALIASES.get(stream, stream)
    if wanted is not None and encoder and encoder != VIDEO_CODECS[wanted]["vcodec"]:
        raise ExportError(f"cannot append: {out} holds {stream} video; choose no video codec, or {stream}")
    try:
        return encoder_config_from_video_info(infos[0])
    except (ValueError, ImportError) as exc:
        raise ExportError(f"cannot append: cannot encode {out}'s video codec {stream}: {first_line(exc)}") from None

