"""``--video``: a LeRobot export's cameras as MP4 files (PyAV), one per episode and camera,
encoded as LeRobot encodes them (src/lerobot/configs/video.py: SVT-AV1, yuv420p, g=2,
crf 30, preset 12; H.264 where PyAV's FFmpeg has no SVT-AV1).  Lossy, unlike the default
PNGs in the parquet."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np

VIDEO_CODECS = ("libsvtav1", "libx264")  # LeRobot's default first


def require_av() -> None:
    try:
        import av  # noqa: F401
    except ImportError:
        raise ImportError("--video needs PyAV: pip install av (or leave --video out: PNG "
                          "images in the parquet need no codec)") from None


def decode_png_column(column) -> np.ndarray:
    """A parquet image column (struct {bytes, path}) -> uint8 (T, H, W, 3)."""
    from PIL import Image

    return np.stack([np.asarray(Image.open(io.BytesIO(v["bytes"])).convert("RGB"))
                     for v in column.to_pylist()])


def encode_video(path: Path, frames: np.ndarray, fps: int) -> str:
    """uint8 (T, H, W, 3) -> MP4 at `fps`; returns the codec's name."""
    import os

    import av

    os.environ.setdefault("SVT_LOG", "1")  # SVT-AV1's banner and warnings: errors only
    codec = next(c for c in VIDEO_CODECS if c in av.codecs_available)
    path.parent.mkdir(parents=True, exist_ok=True)
    h, w = frames.shape[1:3]
    with av.open(str(path), "w") as container:
        options = {"g": "2", "crf": "30"} | ({"preset": "12"} if codec == "libsvtav1" else {})
        stream = container.add_stream(codec, rate=fps, options=options)
        stream.width, stream.height, stream.pix_fmt = w, h, "yuv420p"
        for img in frames:
            container.mux(stream.encode(av.VideoFrame.from_ndarray(
                np.ascontiguousarray(img), format="rgb24")))
        container.mux(stream.encode())
    return codec


def video_info(path: Path, fps: int, version: str) -> dict:
    """A video feature's ``info`` in info.json, probed from the file as LeRobot's
    ``get_video_info`` does (v2.1 flags depth as ``video.is_depth_map``, v3.0 as
    ``is_depth_map``)."""
    import av

    with av.open(str(path)) as f:
        s = f.streams.video[0]
        info = {"video.height": s.height, "video.width": s.width,
                "video.codec": s.codec_context.codec.canonical_name,
                "video.pix_fmt": s.codec_context.pix_fmt, "video.fps": int(fps)}
    depth = {"video.is_depth_map": False} if version == "v2.1" else {"is_depth_map": False}
    return {**info, **depth, "video.channels": 3, "has_audio": False}


def decode_video(path: Path) -> np.ndarray:
    """Every frame of an MP4, uint8 (T, H, W, 3)."""
    import av

    with av.open(str(path)) as f:
        return np.stack([fr.to_ndarray(format="rgb24") for fr in f.decode(video=0)])
