"""Frames from a video file or a folder of images (docs/dataset_format.md §8).

``read_frames`` decodes with OpenCV (``cv2.VideoCapture``; any container and codec the
installed OpenCV reads) or reads the images of a folder in name order (png, jpg, jpeg, bmp,
tif, tiff, webp), keeps every ``stride``-th frame between ``start`` and ``end`` seconds (video
only) up to ``max_frames``, and resizes to ``size`` = (W, H) by area averaging (shrinking) or
bilinear interpolation (enlarging). Frames come back as uint8 RGB (H, W, 3).
"""
from __future__ import annotations

import numbers
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from d2gs_np.base.checks import check_number

__all__ = ["IMAGE_EXTENSIONS", "MIN_FRAMES", "DecodedFrames", "read_frames", "check_decode_args"]

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp")
MIN_FRAMES = 3  # fewer frames give no trajectory to speak of (and the trajectory metrics need 3)


@dataclass
class DecodedFrames:
    images: list  # uint8 RGB (H, W, 3), the kept frames
    source_index: list  # index of each kept frame in the source (video frame number or file order)
    names: list  # file name (folder) or "frame N" (video)
    fps: float  # frames per second of the video (None for a folder)
    source_size: tuple  # (W, H) before resizing
    num_read: int  # frames read from the source


def _int_arg(v, name, lo, allow_none=False):
    if v is None and allow_none:
        return None
    if isinstance(v, bool) or not isinstance(v, numbers.Integral):
        raise TypeError(f"{name} must be an int; got {type(v).__name__} {v!r}")
    if v < lo:
        raise ValueError(f"{name} must be >= {lo}; got {v}")
    return int(v)


def check_decode_args(source, stride=1, max_frames=None, size=None, start=None, end=None):
    """Validate the arguments of ``read_frames`` without reading anything; returns the source Path."""
    src = Path(source)
    if not src.exists():
        raise FileNotFoundError(f"video or image folder {src} does not exist; pass an existing .mp4/.avi/.mov file "
                                "or a folder of images")
    _int_arg(stride, "stride", 1)
    _int_arg(max_frames, "max_frames", MIN_FRAMES, allow_none=True)
    if size is not None:
        if (not isinstance(size, tuple) or len(size) != 2
                or not all(isinstance(s, numbers.Integral) and not isinstance(s, bool) for s in size)):
            raise TypeError(f"size must be a tuple (W, H) of ints; got {size!r}")
        if min(size) < 16:
            raise ValueError(f"size (W, H) must be at least 16 x 16 pixels; got {size}")
    for name, v in (("start", start), ("end", end)):
        if v is not None:
            check_number(v, name, 0.0, hint="a time in seconds")
    if start is not None and end is not None and end <= start:
        raise ValueError(f"end ({end} s) must be after start ({start} s)")
    if src.is_dir() and (start is not None or end is not None):
        raise ValueError(f"start/end (seconds) apply to a video file, but {src} is a folder of images; "
                         "choose frames with stride / max_frames, or remove files from the folder")
    return src


def _resize(img, size):
    if size is None or (img.shape[1], img.shape[0]) == tuple(size):
        return img
    shrink = size[0] < img.shape[1]
    return cv2.resize(img, tuple(size), interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR)


def _folder_frames(src):
    files = sorted(p for p in src.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_EXTENSIONS)
    if not files:
        raise ValueError(f"folder {src} holds no images ({', '.join(IMAGE_EXTENSIONS)}); pass a folder of frames "
                         "or a video file")
    for i, p in enumerate(files):
        img = cv2.imread(str(p), cv2.IMREAD_COLOR)
        if img is None:
            raise ValueError(f"could not read image {p} (corrupt or unsupported); remove or re-save it")
        yield i, p.name, img


def _video_frames(src, first, last):
    cap = cv2.VideoCapture(str(src))
    try:
        if not cap.isOpened():
            raise ValueError(f"could not open {src} as a video (not a video file, or a codec this OpenCV build "
                             "lacks); convert it to .mp4 (H.264) or .avi (MJPG), or extract its frames to a folder")
        i = 0
        while last is None or i < last:
            ok, img = cap.read()
            if not ok:
                if i == 0:
                    raise ValueError(f"{src} opened as a video but no frame could be decoded; the file is "
                                     "truncated or its codec is not supported: convert it or extract its frames")
                break
            if i >= first:
                yield i, f"frame {i}", img
            i += 1
    finally:
        cap.release()


def read_frames(source, stride=1, max_frames=None, size=None, start=None, end=None, log=None) -> DecodedFrames:
    """Decode ``source`` (video file or image folder) into kept, resized uint8 RGB frames.

    stride: keep every stride-th frame. max_frames: stop after this many kept frames. size: (W, H)
    output size (default: the source's). start, end: seconds into a video. log: callable for
    progress lines (or None). Raises FileNotFoundError / ValueError / TypeError with the fix.
    """
    src = check_decode_args(source, stride, max_frames, size, start, end)
    fps = None
    if src.is_dir():
        it = _folder_frames(src)
    else:
        cap = cv2.VideoCapture(str(src))
        fps = float(cap.get(cv2.CAP_PROP_FPS)) if cap.isOpened() else 0.0
        cap.release()
        if (start is not None or end is not None) and not fps > 0:
            raise ValueError(f"{src} reports no frame rate, so start/end in seconds cannot be used; use stride / "
                             "max_frames")
        first = int(round(start * fps)) if start is not None else 0
        last = int(round(end * fps)) if end is not None else None
        it = _video_frames(src, first, last)
    images, index, names = [], [], []
    src_size = None
    n_read = 0
    base = None
    for i, name, bgr in it:
        n_read += 1
        base = i if base is None else base
        if src_size is None:
            src_size = (bgr.shape[1], bgr.shape[0])
        elif (bgr.shape[1], bgr.shape[0]) != src_size and size is None:
            raise ValueError(f"{name} is {bgr.shape[1]}x{bgr.shape[0]} but the first frame is {src_size[0]}x"
                             f"{src_size[1]}; all frames need one size: pass size (--size WxH) to resize them")
        if (i - base) % stride:
            continue
        images.append(np.ascontiguousarray(_resize(bgr, size)[:, :, ::-1]))
        index.append(i)
        names.append(name)
        if log is not None and len(images) % 10 == 0:
            log(f"decoding: {n_read} frames read, {len(images)} kept")
        if max_frames is not None and len(images) >= max_frames:
            break
    if len(images) < MIN_FRAMES:
        raise ValueError(f"only {len(images)} frame(s) kept from {src} ({n_read} read, stride {stride}); need at "
                         f"least {MIN_FRAMES}: lower the stride, widen start/end, or use a longer video")
    if log is not None:
        log(f"decoded {src}: {n_read} frames read, {len(images)} kept (stride {stride}), "
            f"{images[0].shape[1]}x{images[0].shape[0]} pixels")
    return DecodedFrames(images, index, names, fps, src_size, n_read)
