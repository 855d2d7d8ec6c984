"""The sequence folder (SPEC §6): reader, writer and validator.

Every input (synthetic, KITTI, nuScenes, a user's own drive) becomes one such folder,
and every stage reads it. Errors name the file and the problem.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image

from pavemap.errors import SequenceError
from pavemap.io.atomic import atomic_write_json
from pavemap.types import (
    NUM_DEFECT_CLASSES,
    Camera,
    Detection,
    Frame,
    GeoOrigin,
    SemanticClass,
    Sequence,
    View,
)

FORMAT = "pavemap-sequence/1"
SEQUENCE_FILE = "sequence.json"
DETECTIONS_FILE = "detections.jsonl"

__all__ = ["SequenceError"]  # re-exported: its home is pavemap.errors


@dataclass(frozen=True)
class Problem:
    file: str
    message: str

    def __str__(self) -> str:
        return f"{self.file}: {self.message}"


# ---------------------------------------------------------------------------- parsing


def _matrix(value: object, shape: tuple[int, int], where: str, file: Path) -> np.ndarray:
    try:
        m = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise SequenceError(file, f"{where} is not a numeric matrix ({e})") from None
    if m.shape != shape:
        raise SequenceError(file, f"{where} must be {shape[0]}x{shape[1]}, got shape {list(m.shape)}")
    return m


def check_intrinsics(K: np.ndarray) -> str | None:
    """Return why ``K`` is not a valid pinhole matrix, or None."""
    if K.shape != (3, 3):
        return f"K must be 3x3, got shape {list(K.shape)}"
    if not np.all(np.isfinite(K)):
        return "K contains NaN or infinity"
    if abs(K[1, 0]) > 1e-9 or abs(K[2, 0]) > 1e-9 or abs(K[2, 1]) > 1e-9:
        return "K is not upper-triangular"
    if abs(K[2, 2] - 1.0) > 1e-6:
        return f"K[2][2] must be 1, got {K[2, 2]:g}"
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        return f"K focal lengths must be positive, got fx={K[0, 0]:g}, fy={K[1, 1]:g}"
    return None


def check_pose(T: np.ndarray, tol: float = 1e-4) -> str | None:
    """Return why ``T`` (4x4) is not a rigid camera-to-world transform, or None."""
    if T.shape != (4, 4):
        return f"pose must be 4x4, got shape {list(T.shape)}"
    if not np.all(np.isfinite(T)):
        return "pose contains NaN or infinity"
    R = T[:3, :3]
    err = np.abs(R @ R.T - np.eye(3)).max()
    if err > tol:
        return f"pose rotation is not orthonormal (max |R R^T - I| = {err:.2e})"
    det = np.linalg.det(R)
    if abs(det - 1.0) > tol:
        return f"pose rotation has det {det:.4f}, expected 1 (a reflection?)"
    if np.abs(T[3] - np.array([0, 0, 0, 1.0])).max() > 1e-9:
        return "pose bottom row must be [0, 0, 0, 1]"
    return None


def sequence_from_dict(d: dict, root: Path | None = None) -> Sequence:
    """Build a Sequence from the parsed ``sequence.json``; structural errors raise SequenceError."""
    file = (root / SEQUENCE_FILE) if root is not None else Path(SEQUENCE_FILE)
    if not isinstance(d, dict):
        raise SequenceError(file, "top level must be a JSON object")
    fmt = d.get("format")
    if fmt != FORMAT:
        raise SequenceError(file, f"'format' must be {FORMAT!r}, got {fmt!r}")
    for key in ("name", "classes", "cameras", "frames"):
        if key not in d:
            raise SequenceError(file, f"missing key {key!r}")

    classes = []
    seen_ids: set[int] = set()
    for i, c in enumerate(d["classes"]):
        try:
            cid = int(c["id"])
            sc = SemanticClass(
                id=cid,
                name=str(c["name"]),
                road=bool(c.get("road", False)),
                movable=bool(c.get("movable", False)),
                sky=bool(c.get("sky", False)),
            )
        except (KeyError, TypeError, ValueError) as e:
            raise SequenceError(file, f"classes[{i}] needs 'id' and 'name' ({e})") from None
        if not 0 <= cid <= 255:
            raise SequenceError(file, f"classes[{i}] id {cid} outside 0..255 (labels are uint8)")
        if cid in seen_ids:
            raise SequenceError(file, f"classes[{i}] repeats id {cid}")
        seen_ids.add(cid)
        classes.append(sc)

    cameras: dict[str, Camera] = {}
    if not isinstance(d["cameras"], dict) or not d["cameras"]:
        raise SequenceError(file, "'cameras' must be a non-empty object of name -> camera")
    for name, c in d["cameras"].items():
        where = f"cameras.{name}"
        try:
            w, h = int(c["width"]), int(c["height"])
        except (KeyError, TypeError, ValueError):
            raise SequenceError(file, f"{where} needs integer 'width' and 'height'") from None
        if w <= 0 or h <= 0:
            raise SequenceError(file, f"{where} has non-positive size {w}x{h}")
        K = np.asarray(c.get("K"), dtype=np.float64) if c.get("K") is not None else np.zeros(0)
        why = check_intrinsics(K)
        if why:
            raise SequenceError(file, f"{where}: {why}")
        cameras[name] = Camera(name, w, h, K)

    frames: list[Frame] = []
    last_index: int | None = None
    for fi, f in enumerate(d["frames"]):
        where = f"frames[{fi}]"
        try:
            index = int(f["index"])
        except (KeyError, TypeError, ValueError):
            raise SequenceError(file, f"{where} needs an integer 'index'") from None
        if last_index is not None and index == last_index:
            raise SequenceError(file, f"{where} repeats frame index {index}")
        if last_index is not None and index < last_index:
            raise SequenceError(file, f"{where} index {index} decreases (previous {last_index})")
        last_index = index
        ts = float(f.get("timestamp", float(index)))
        views: dict[str, View] = {}
        for cam, v in (f.get("views") or {}).items():
            vwhere = f"{where}.views.{cam}"
            if cam not in cameras:
                raise SequenceError(file, f"{vwhere}: unknown camera {cam!r}; cameras are {sorted(cameras)}")
            if "image" not in v:
                raise SequenceError(file, f"{vwhere} has no 'image'")
            T = _matrix(v.get("T_world_cam"), (4, 4), f"{vwhere}.T_world_cam", file)
            why = check_pose(T)
            if why:
                raise SequenceError(file, f"{vwhere}: {why}")
            views[cam] = View(cam, str(v["image"]), T, v.get("semantics"), v.get("depth"))
        if not views:
            raise SequenceError(file, f"{where} has no views")
        frames.append(Frame(index, ts, views))

    geo = d.get("geo_origin")
    geo_origin = None
    if geo is not None:
        try:
            geo_origin = GeoOrigin(
                lat=float(geo["lat"]),
                lon=float(geo["lon"]),
                alt=float(geo.get("alt", 0.0)),
                heading_deg=float(geo.get("heading_deg", 90.0)),
            )
        except (KeyError, TypeError, ValueError):
            raise SequenceError(file, "geo_origin needs numeric 'lat' and 'lon'") from None
        if not (-90 <= geo_origin.lat <= 90 and -180 <= geo_origin.lon <= 180):
            raise SequenceError(file, f"geo_origin lat/lon out of range: {geo_origin.lat}, {geo_origin.lon}")
    return Sequence(str(d["name"]), classes, cameras, frames, geo_origin, root)


def sequence_to_dict(seq: Sequence) -> dict:
    return {
        "format": FORMAT,
        "name": seq.name,
        "geo_origin": None
        if seq.geo_origin is None
        else {
            "lat": seq.geo_origin.lat,
            "lon": seq.geo_origin.lon,
            "alt": seq.geo_origin.alt,
            "heading_deg": seq.geo_origin.heading_deg,
        },
        "classes": [
            {"id": c.id, "name": c.name, "road": c.road, "movable": c.movable, "sky": c.sky}
            for c in seq.classes
        ],
        "cameras": {
            n: {"width": c.width, "height": c.height, "K": np.asarray(c.K, dtype=float).tolist()}
            for n, c in seq.cameras.items()
        },
        "frames": [
            {
                "index": f.index,
                "timestamp": f.timestamp,
                "views": {
                    cam: {
                        "image": v.image,
                        "T_world_cam": np.asarray(v.T_world_cam, dtype=float).tolist(),
                        "semantics": v.semantics,
                        "depth": v.depth,
                    }
                    for cam, v in f.views.items()
                },
            }
            for f in seq.frames
        ],
    }


# ---------------------------------------------------------------------------- public API


def read_sequence(root: str | os.PathLike, validate: bool = True) -> Sequence:
    """Read ``root/sequence.json``. With ``validate``, also check files on disk (raises on the first problems)."""
    root = Path(root)
    file = root / SEQUENCE_FILE
    try:
        is_dir = root.is_dir()
    except OSError as e:  # e.g. a name too long for the file system
        raise SequenceError(root, f"cannot be read as a folder ({e.strerror})") from None
    if not is_dir:
        raise SequenceError(root, "is not a folder (expected a sequence folder holding sequence.json)")
    if not file.is_file():
        raise SequenceError(file, "not found; is this a pavemap sequence folder? (see README: sequence folder)")
    try:
        d = json.loads(file.read_text(encoding="utf-8"))
    except json.JSONDecodeError as e:
        raise SequenceError(file, f"invalid JSON at line {e.lineno}, column {e.colno}: {e.msg}") from None
    seq = sequence_from_dict(d, root)
    if validate:
        problems = validate_sequence(seq)
        if problems:
            # validate_sequence stops at 50 problems, so past that the count is a lower bound
            rest = len(problems) - 3
            more = f" (and {rest}{'+' if len(problems) >= 50 else ''} more)" if rest > 0 else ""
            first = problems[0]
            raise SequenceError(
                first.file, first.message + "".join(f"; {p}" for p in problems[1:3]) + more
            )
    return seq


def write_sequence(seq: Sequence, root: str | os.PathLike | None = None) -> Path:
    """Write ``sequence.json`` (atomically). Images and layers are written by the producer."""
    root = Path(root) if root is not None else seq.root
    if root is None:
        raise ValueError("write_sequence needs a root folder")
    root.mkdir(parents=True, exist_ok=True)
    seq.root = root
    return atomic_write_json(root / SEQUENCE_FILE, sequence_to_dict(seq))


def validate_sequence(seq: Sequence, check_images: bool = True, max_problems: int = 50) -> list[Problem]:
    """Check the files a sequence refers to. Returns problems (file, message); empty when valid."""
    assert seq.root is not None
    problems: list[Problem] = []

    def add(file: str | Path, msg: str) -> bool:
        problems.append(Problem(str(file), msg))
        return len(problems) >= max_problems

    for f in seq.frames:
        for cam, v in f.views.items():
            c = seq.cameras[cam]
            for kind, rel in (("image", v.image), ("semantics", v.semantics), ("depth", v.depth)):
                if rel is None:
                    continue
                p = seq.root / rel
                if not p.is_file():
                    if add(p, f"{kind} missing (frame {f.index}, camera {cam})"):
                        return problems
                    continue
                if not check_images:
                    continue
                try:
                    with Image.open(p) as im:
                        size = im.size
                except OSError as e:
                    if add(p, f"unreadable {kind} ({e})"):
                        return problems
                    continue
                if size != (c.width, c.height):
                    msg = f"{kind} is {size[0]}x{size[1]}, camera {cam} is {c.width}x{c.height}"
                    if add(p, msg):
                        return problems
    det_file = seq.root / DETECTIONS_FILE
    if det_file.is_file():
        try:
            read_detections(det_file)
        except SequenceError as e:
            add(e.file, e.problem)
    return problems


# ---------------------------------------------------------------------------- layers


def load_rgb(path: str | os.PathLike) -> np.ndarray:
    """(H, W, 3) uint8; grey images become 3 channels."""
    try:
        with Image.open(path) as im:
            return np.asarray(im.convert("RGB"))
    except (OSError, ValueError) as e:
        raise SequenceError(path, f"cannot read image ({e})") from None


def load_semantics(path: str | os.PathLike) -> np.ndarray:
    """(H, W) uint8 class ids."""
    try:
        with Image.open(path) as im:
            if im.mode not in ("L", "P", "I", "I;16"):
                raise SequenceError(path, f"semantic map must be a single-channel PNG, got mode {im.mode}")
            a = np.asarray(im)
    except OSError as e:
        raise SequenceError(path, f"cannot read semantic map ({e})") from None
    if a.dtype != np.uint8:
        if a.max(initial=0) > 255:
            raise SequenceError(path, "semantic ids above 255")
        a = a.astype(np.uint8)
    return a


def load_depth(path: str | os.PathLike) -> np.ndarray:
    """(H, W) float32 metres, 0 = unknown (stored as uint16 millimetres)."""
    try:
        with Image.open(path) as im:
            a = np.asarray(im)
    except OSError as e:
        raise SequenceError(path, f"cannot read depth map ({e})") from None
    return a.astype(np.float32) / 1000.0


def save_depth(path: str | os.PathLike, depth_m: np.ndarray) -> None:
    mm = np.clip(np.nan_to_num(depth_m, nan=0.0, posinf=0.0) * 1000.0 + 0.5, 0, 65535).astype(np.uint16)
    Image.fromarray(mm).save(path)


# ---------------------------------------------------------------------------- detections


def read_detections(path: str | os.PathLike) -> list[Detection]:
    """Read ``detections.jsonl``. Malformed lines and unknown class ids raise, naming file and line.

    Values that are well-formed but unusable (boxes outside the image, NaN confidence, a
    frame that does not exist) are the filter's business: it skips and counts them.
    """
    path = Path(path)
    dets: list[Detection] = []
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except OSError as e:
        raise SequenceError(path, f"cannot read detections ({e})") from None
    for ln, line in enumerate(lines, 1):
        if not line.strip():
            continue
        try:
            d = json.loads(line)
            box = tuple(float(x) for x in d["box"])
            if len(box) != 4:
                raise ValueError("box must have 4 numbers x1, y1, x2, y2")
            cls = int(d["cls"])
            conf = float(d["conf"])
            det = Detection(int(d["frame"]), str(d["camera"]), box, cls, conf)  # type: ignore[arg-type]
        except (json.JSONDecodeError, KeyError, TypeError, ValueError) as e:
            raise SequenceError(path, f"line {ln}: not a detection record ({e})") from None
        if not 0 <= cls < NUM_DEFECT_CLASSES:
            raise SequenceError(path, f"line {ln}: unknown class id {cls} (valid: 0 D00, 1 D10, 2 D20, 3 D40)")
        dets.append(det)
    return dets


def write_detections(path: str | os.PathLike, detections: list[Detection], extra: list[dict] | None = None) -> Path:
    """Write detections as JSONL (atomically). ``extra`` adds per-line fields (e.g. a backend's ids)."""
    from pavemap.io.atomic import atomic_write_text

    out = []
    for i, d in enumerate(detections):
        rec = {
            "frame": d.frame,
            "camera": d.camera,
            "box": [round(float(x), 2) for x in d.box],
            "cls": int(d.cls),
            "conf": round(float(d.conf), 4) if math.isfinite(d.conf) else d.conf,
        }
        if extra is not None:
            rec.update(extra[i])
        out.append(json.dumps(rec))
    return atomic_write_text(path, "\n".join(out) + ("\n" if out else ""))
