"""Write frames (from `dbdjax.render`) to image and video files.

Not imported by `import dbdjax`: its dependencies are optional and imported when a file is written.
GIF and PNG need Pillow (`pip install pillow`, part of the `dev` and `envs` extras); MP4 and other
video containers need mediapy and an ffmpeg executable on PATH (`pip install mediapy`, ffmpeg from
your system's packages).
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np

_FFMPEG = (".mp4", ".webm", ".mkv", ".mov", ".avi")


def _as_frames(frames) -> np.ndarray:
    """(T, H, W, 3) uint8 numpy array (from any array-like, e.g. a jax array)."""
    frames = np.asarray(frames)
    if frames.ndim != 4 or frames.shape[-1] != 3 or frames.shape[0] == 0:
        raise ValueError(f"frames must be (T, H, W, 3) with T >= 1, got shape {frames.shape}")
    if frames.dtype != np.uint8:
        raise ValueError(f"frames must be uint8 (as `render` returns), got {frames.dtype}")
    return frames


def _pillow():
    try:
        from PIL import Image
    except ImportError as error:
        raise ImportError("writing GIF/PNG needs Pillow: pip install pillow (or the dbdjax[dev] extra)") from error
    return Image


def save_image(frame, path: str | Path) -> Path:
    """Write one frame (H, W, 3) uint8 as an image (PNG, or any format Pillow knows by the suffix).
    Returns the path."""
    path = Path(path)
    frames = _as_frames(np.asarray(frame)[None])
    path.parent.mkdir(parents=True, exist_ok=True)
    _pillow().fromarray(frames[0]).save(path)
    return path


def save_video(frames, path: str | Path, fps: float = 30.0) -> Path:
    """Write frames (T, H, W, 3) uint8 to `path`: .gif through Pillow, .mp4/.webm/.mkv/.mov/.avi
    through mediapy + ffmpeg. Returns the path.

    GIF stores frame times in hundredths of a second, so fps is rounded to 100 / round(100 / fps)
    (30 fps plays at 33.3); Pillow merges identical consecutive frames into one longer frame (the
    playing time is kept, the frame count drops). Every frame is quantised to its own 256-colour
    palette. Raises ImportError / RuntimeError naming what is missing (Pillow, mediapy, ffmpeg).
    """
    path = Path(path)
    frames = _as_frames(frames)
    if not fps > 0:
        raise ValueError(f"fps must be positive, got {fps}")
    suffix = path.suffix.lower()
    if suffix == ".gif":
        image = _pillow()
        path.parent.mkdir(parents=True, exist_ok=True)
        pictures = [image.fromarray(frame) for frame in frames]
        duration = max(10, int(round(100.0 / fps)) * 10)  # ms, a multiple of GIF's 10 ms tick
        pictures[0].save(path, save_all=True, append_images=pictures[1:], duration=duration, loop=0)
        return path
    if suffix in _FFMPEG:
        try:
            import mediapy
        except ImportError as error:
            raise ImportError(
                f"writing {suffix} needs mediapy (pip install mediapy) and ffmpeg; or write a .gif (Pillow)"
            ) from error
        if shutil.which("ffmpeg") is None:
            raise RuntimeError(
                f"writing {suffix} needs an ffmpeg executable on PATH (e.g. apt install ffmpeg); "
                "or write a .gif (Pillow)"
            )
        path.parent.mkdir(parents=True, exist_ok=True)
        mediapy.write_video(str(path), frames, fps=fps)
        return path
    raise ValueError(f"unknown video format {suffix!r} for {path}: use .gif or one of {', '.join(_FFMPEG)}")
