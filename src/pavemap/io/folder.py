"""Own drive → sequence folder: a folder of images or a video, a cameras.json and poses.

``cameras.json`` (one entry per camera; ``K`` or ``fx, fy, cx, cy``)::

    {"cameras": {"front": {"width": 1920, "height": 1080,
                           "K": [[1400, 0, 959.5], [0, 1400, 539.5], [0, 0, 1]]}}}

(the top-level ``"cameras"`` wrapper is optional). ``poses.csv`` holds one row per image, camera-to-world
``T_world_cam`` with OpenCV camera axes (x right, y down, z forward) in a metric world with z up; columns:

- ``frame`` (int, optional: default row order), ``camera`` (optional when there is one camera), ``timestamp``
  (seconds, optional), ``image`` (relative to the images folder, optional: the k-th image of that camera by name);
- the pose, either ``tx, ty, tz, qw, qx, qy, qz`` (unit quaternion, scalar first) or ``m00 … m23`` (the top
  three rows of the 4×4, row-major) or ``m00 … m33``.

Images: ``IMAGES_DIR/*.png|jpg`` for one camera, or ``IMAGES_DIR/<camera>/*`` per camera. ``poses sfm`` instead
of a CSV estimates poses from the images with pycolmap (:mod:`pavemap.sfm.pipeline`), metric by the known camera
height above the road, and leaves what it measured in ``sfm.json``.
"""

from __future__ import annotations

import csv
import os
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image

from pavemap.geometry.valid import check_intrinsics, check_pose
from pavemap.io.atomic import atomic_path
from pavemap.io.sequence import SequenceError
from pavemap.palette import PAVEMAP_CLASSES
from pavemap.types import Camera, SemanticClass

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")

#: Label table of a sequence without semantics (same ids as the synthetic world, so a
#: segmenter or label folder mapped with the "pavemap" preset fits it).
DEFAULT_CLASSES: list[SemanticClass] = PAVEMAP_CLASSES


# ----------------------------------------------------------------------------- shared helpers


def image_size(path: str | os.PathLike) -> tuple[int, int]:
    """(width, height) of an image file; unreadable → SequenceError naming the file."""
    try:
        with Image.open(path) as im:
            return im.size
    except FileNotFoundError:
        raise SequenceError(path, "image not found") from None
    except OSError as e:
        raise SequenceError(path, f"unreadable image ({e})") from None


def copy_image(src: str | os.PathLike, dst: str | os.PathLike, to_rgb: bool = False) -> Path:
    """Copy an image into a sequence (atomically). ``to_rgb`` re-encodes grey/other modes as RGB PNG."""
    src, dst = Path(src), Path(dst)
    dst.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(dst) as tmp:
        if to_rgb or src.suffix.lower() not in IMAGE_SUFFIXES:
            try:
                with Image.open(src) as im:
                    im.convert("RGB").save(tmp, format="PNG" if dst.suffix.lower() == ".png" else "JPEG")
            except OSError as e:
                raise SequenceError(src, f"unreadable image ({e})") from None
        else:
            shutil.copyfile(src, tmp)
    return dst


def list_images(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)


def make_pose(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(4, 4) float64 from (3, 3) rotation and (3,) translation."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def quat_to_rot(q: np.ndarray) -> np.ndarray:
    """(N, 4) quaternions w, x, y, z (normalised here) → (N, 3, 3) rotation matrices (scipy's ``Rotation``)."""
    from scipy.spatial.transform import Rotation

    q = np.asarray(q, dtype=np.float64).reshape(-1, 4)
    return Rotation.from_quat(q, scalar_first=True).as_matrix().reshape(-1, 3, 3)


#: How far a quaternion's norm may be from 1: rounding to ~5 digits in a file, not a quaternion that is not one.
QUAT_NORM_TOL = 1e-4


def _quat_pose(v: np.ndarray, path: Path, line: int) -> np.ndarray:
    """(4, 4) pose from ``tx ty tz qw qx qy qz`` (7,); a quaternion of norm other than 1 raises SequenceError."""
    if not np.isfinite(v).all():
        raise SequenceError(path, f"line {line}: the pose holds NaN or infinity ({', '.join(_QUAT)} = "
                                  f"{', '.join(f'{x:g}' for x in v)})")
    norm = float(np.linalg.norm(v[3:]))
    if abs(norm - 1.0) > QUAT_NORM_TOL:
        raise SequenceError(path, f"line {line}: quaternion qw, qx, qy, qz has norm {norm:.6g}, expected 1 (within "
                                  f"{QUAT_NORM_TOL:g}): not a rotation; write unit quaternions")
    return make_pose(quat_to_rot(v[3:])[0], v[:3])


# ----------------------------------------------------------------------------- cameras.json


def read_cameras_json(path: str | os.PathLike) -> dict[str, Camera]:
    """Parse ``cameras.json`` → {name: Camera}; problems raise SequenceError naming the file."""
    from pavemap.io.schema import load_json  # the one JSON reader of user files: duplicate keys refused

    path = Path(path)
    if not path.is_file():
        raise SequenceError(path, "cameras file not found")
    d = load_json(path)
    if isinstance(d, dict) and isinstance(d.get("cameras"), dict):
        d = d["cameras"]
    if not isinstance(d, dict) or not d:
        raise SequenceError(path, "expected {camera name: {width, height, K | fx, fy, cx, cy}}")
    cams: dict[str, Camera] = {}
    for name, c in d.items():
        try:
            w, h = int(c["width"]), int(c["height"])
            if "K" in c:
                K = np.asarray(c["K"], dtype=np.float64)
            else:
                K = np.array([[c["fx"], 0, c["cx"]], [0, c.get("fy", c["fx"]), c["cy"]], [0, 0, 1]], float)
        except (KeyError, TypeError, ValueError) as e:
            raise SequenceError(path, f"camera {name!r} needs width, height and K or fx, fy, cx, cy ({e})") from None
        why = check_intrinsics(K)
        if why:
            raise SequenceError(path, f"camera {name!r}: {why}")
        cams[str(name)] = Camera(str(name), w, h, K)
    return cams


# ----------------------------------------------------------------------------- poses.csv


@dataclass
class PoseRow:
    frame: int
    camera: str | None
    timestamp: float | None
    image: str | None
    T: np.ndarray  # (4, 4) float64 camera-to-world


_QUAT = ("tx", "ty", "tz", "qw", "qx", "qy", "qz")
_M12 = tuple(f"m{r}{c}" for r in range(3) for c in range(4))
_M16 = tuple(f"m{r}{c}" for r in range(4) for c in range(4))


def read_poses_csv(path: str | os.PathLike) -> list[PoseRow]:
    """Parse ``poses.csv`` (schema in the module docstring); bad rows raise naming file and line."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise SequenceError(path, "poses file not found") from None
    rows = list(csv.DictReader(line for line in text.splitlines() if line.strip() and not line.startswith("#")))
    if not rows:
        raise SequenceError(path, "no pose rows (expected a header line and one row per image)")
    cols = {c.strip() for c in rows[0]}
    if set(_QUAT) <= cols:
        kind = "quat"
    elif set(_M12) <= cols:
        kind = "m16" if set(_M16) <= cols else "m12"
    else:
        raise SequenceError(
            path, f"needs pose columns {', '.join(_QUAT)} or m00..m23 (row-major 3x4/4x4); got {sorted(cols)}"
        )
    out: list[PoseRow] = []
    for i, r in enumerate(rows):
        r = {k.strip(): (v.strip() if isinstance(v, str) else v) for k, v in r.items() if k is not None}
        line = i + 2
        try:
            if kind == "quat":
                T = _quat_pose(np.array([float(r[c]) for c in _QUAT]), path, line)
            else:
                names = _M16 if kind == "m16" else _M12
                m = np.array([float(r[c]) for c in names]).reshape(-1, 4)
                T = np.eye(4)
                T[: m.shape[0]] = m
            frame = int(r["frame"]) if r.get("frame") not in (None, "") else i
            ts = float(r["timestamp"]) if r.get("timestamp") not in (None, "") else None
        except SequenceError:
            raise
        except (KeyError, ValueError) as e:
            raise SequenceError(path, f"line {line}: bad value ({e})") from None
        why = check_pose(T, tol=QUAT_NORM_TOL)
        if why:
            raise SequenceError(path, f"line {line}: {why}")
        # re-orthonormalise rounding (within the tolerance) so the stored pose is a rotation to float precision
        U, _, Vt = np.linalg.svd(T[:3, :3])
        T[:3, :3] = U @ Vt
        out.append(PoseRow(frame, r.get("camera") or None, ts, r.get("image") or None, T))
    return out


# ----------------------------------------------------------------------------- folder import
