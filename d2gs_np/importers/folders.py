"""What every importer does with files: check the output folder before any work, list and read
the images of a folder, resize to the scene's size.

Images come back as float64 RGB (H, W, 3) in [0, 1]: 8-bit (value / 255) or 16-bit (value /
65535), greyscale repeated into RGB. An alpha channel that is opaque everywhere is dropped; one
with transparent pixels is refused, as ``load_scene`` refuses RGBA, rather than composited onto a
guessed background.
"""
from __future__ import annotations

import json
import os
from pathlib import Path

import cv2
import numpy as np

__all__ = ["IMAGE_EXTENSIONS", "check_out_folder", "list_images", "read_rgb", "read_grey", "resize_to"]

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp")


def check_out_folder(out, overwrite) -> Path:
    """The output scene folder as a Path; ValueError if it is a file, or a non-empty folder without
    ``overwrite``."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise ValueError(f"output scene folder {out} is a file; choose a folder path")
    if out.is_dir() and any(out.iterdir()) and not overwrite:
        raise ValueError(f"output scene folder {out} exists and is not empty; choose a new folder or pass --overwrite")
    return out


def list_images(folder, what, extensions=IMAGE_EXTENSIONS) -> list:
    """Image files of ``folder`` (by extension, case-insensitive) sorted by name; FileNotFoundError
    naming ``what`` when the folder is missing."""
    folder = Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"{what} folder {folder} does not exist")
    return sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in extensions)


def _decode(path, what):
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{what} {path} does not exist")
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise ValueError(f"{what} {path} cannot be decoded by OpenCV; re-save it as PNG or JPEG")
    if img.dtype == np.uint8:
        scale = 255.0
    elif img.dtype == np.uint16:
        scale = 65535.0
    else:
        raise ValueError(f"{what} {path} has {img.dtype} pixels; save it with 8 or 16 bits per channel")
    return img, scale


def read_rgb(path, what="image") -> np.ndarray:
    """float64 RGB (H, W, 3) in [0, 1] of an image file (module docstring)."""
    img, scale = _decode(path, what)
    if img.ndim == 2:
        img = np.repeat(img[:, :, None], 3, axis=2)
    elif img.shape[2] == 4:
        if np.any(img[:, :, 3] < scale):
            raise ValueError(f"{what} {path} has transparent pixels (an alpha channel); composite it onto the "
                             "background you mean and save it as RGB")
        img = img[:, :, :3]
    elif img.shape[2] != 3:
        raise ValueError(f"{what} {path} has {img.shape[2]} channels; expected RGB (3) or greyscale")
    return img[:, :, ::-1].astype(np.float64) / scale  # OpenCV decodes BGR


def read_grey(path, what="mask") -> np.ndarray:
    """float64 (H, W) in [0, 1] of a greyscale image (colour images: their first channel)."""
    img, scale = _decode(path, what)
    if img.ndim == 3:
        img = img[:, :, 0]
    return img.astype(np.float64) / scale


def resize_to(img, width, height, nearest=False) -> np.ndarray:
    """``img`` (H, W[, C]) at (width, height): area averaging (OpenCV INTER_AREA), or nearest
    neighbour for masks; unchanged when already that size."""
    if img.shape[1] == width and img.shape[0] == height:
        return img
    interp = cv2.INTER_NEAREST if nearest else cv2.INTER_AREA
    return cv2.resize(img, (int(width), int(height)), interpolation=interp)


REPORT_FILE = "import_report.json"


def write_report(out, report: dict) -> Path:
    """Write an importer's report to OUT/import_report.json atomically (a reader never sees half)."""
    path = Path(out) / REPORT_FILE
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(report, indent=2) + "\n", encoding="utf-8")
    os.replace(tmp, path)
    return path
