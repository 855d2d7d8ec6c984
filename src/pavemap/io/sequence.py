"""The sequence folder (SPEC §6): reader, writer and validator.

Every input (synthetic, KITTI, nuScenes, a user's own drive) becomes one such folder, and every stage reads it.
Errors name the file and the problem."""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from PIL import Image

from pavemap.errors import SequenceError
from pavemap.geometry.valid import check_intrinsics, check_pose
from pavemap.io.atomic import atomic_write_json
from pavemap.io.jsonfile import decode_utf8, load_json, parse_json
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
    frame: int | None = None  # the frame whose file it is (None: a file of the whole sequence)

    def __str__(self) -> str:
        return f"{self.file}: {self.message}"


# ---------------------------------------------------------------------------- parsing


def sequence_from_dict(d: object, root: Path | None = None) -> Sequence:
    """Build a Sequence from the parsed ``sequence.json``.

    The schema (:mod:`pavemap.io.schema`) checks types, finite numbers, shapes and lengths first; then
    the meaning: K a pinhole matrix, poses rigid, class ids unique, views of known cameras, frame
    indices increasing. Any problem raises SequenceError naming the JSON path.
    """
    from pavemap.io.schema import issues_text, parse_sequence  # pydantic loads here: the CLI starts 60 ms sooner

    file = (root / SEQUENCE_FILE) if root is not None else Path(SEQUENCE_FILE)
    if isinstance(d, dict) and d.get("format") != FORMAT:  # the most useful message for a foreign file
        raise SequenceError(file, f"'format' must be {FORMAT!r}, got {d.get('format')!r}")
    doc, issues = parse_sequence(d)
    if doc is None:
        raise SequenceError(file, issues_text(issues))

    classes = []
    seen_ids: set[int] = set()
    for i, c in enumerate(doc.classes):
        if c.id in seen_ids:
            raise SequenceError(file, f"classes[{i}].id: repeats id {c.id}")
        seen_ids.add(c.id)
        classes.append(SemanticClass(c.id, c.name, road=c.road, movable=c.movable, sky=c.sky))

    cameras: dict[str, Camera] = {}
    for name, cam in doc.cameras.items():
        K = np.asarray(cam.K, dtype=np.float64)
        why = check_intrinsics(K)
        if why:
            raise SequenceError(file, f"cameras.{name}.K: {why}")
        cameras[name] = Camera(name, cam.width, cam.height, K, cam.ego_mask, cam.height_m)

    frames: list[Frame] = []
    last_index: int | None = None
    last_t: float | None = None
    for fi, f in enumerate(doc.frames):
        where = f"frames[{fi}]"
        index = f.index
        if last_index is not None and index == last_index:
            raise SequenceError(file, f"{where}.index: repeats frame index {index}")
        if last_index is not None and index < last_index:
            raise SequenceError(file, f"{where}.index: {index} decreases (previous {last_index})")
        t = f.timestamp if f.timestamp is not None else float(index)
        if last_t is not None and t < last_t:  # pose interpolation, GPS matching and the EMA all assume time order
            raise SequenceError(file, f"{where}.timestamp: {t} is earlier than frame {last_index}'s {last_t}: frames "
                                "out of order in time (frame indices must follow the capture time)")
        last_index, last_t = index, t
        views: dict[str, View] = {}
        for cam_name, v in f.views.items():
            vwhere = f"{where}.views.{cam_name}"
            if cam_name not in cameras:
                raise SequenceError(file, f"{vwhere}: unknown camera {cam_name!r}; cameras are {sorted(cameras)}")
            T = np.asarray(v.T_world_cam, dtype=np.float64)
            why = check_pose(T)
            if why:
                raise SequenceError(file, f"{vwhere}.T_world_cam: {why}")
            views[cam_name] = View(cam_name, v.image, T, v.semantics, v.depth)
        frames.append(Frame(index, t, views))

    geo, geo_origin = doc.geo_origin, None
    if geo is not None:
        geo_origin = GeoOrigin(lat=geo.lat, lon=geo.lon, alt=geo.alt, heading_deg=geo.heading_deg,
                               georef=geo.georef if isinstance(geo.georef, dict) else None)
    return Sequence(doc.name, classes, cameras, frames, geo_origin, root)


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
            **({"georef": seq.geo_origin.georef} if seq.geo_origin.georef else {}),  # how it was fitted (GPS)
        },
        "classes": [
            {"id": c.id, "name": c.name, "road": c.road, "movable": c.movable, "sky": c.sky}
            for c in seq.classes
        ],
        "cameras": {
            n: {"width": c.width, "height": c.height, "K": np.asarray(c.K, dtype=float).tolist(),
                **({"ego_mask": c.ego_mask} if c.ego_mask else {}),  # masks/<camera>.png, 255 = ego vehicle
                **({"height_m": float(c.height_m)} if c.height_m is not None else {})}
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
    except (OSError, ValueError) as e:  # a name too long for the file system, a NUL byte
        raise SequenceError(root, f"cannot be read as a folder ({getattr(e, 'strerror', None) or e})") from None
    if not is_dir:
        raise SequenceError(root, "is not a folder (expected a sequence folder holding sequence.json)")
    if not file.is_file():
        raise SequenceError(file, "not found; is this a pavemap sequence folder? (see docs/guide/sequence-folder.md)")
    seq = sequence_from_dict(load_json(file), root)
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


#: PIL modes a layer may have: semantics are 8-bit class ids (16-bit accepted when ids stay <= 255),
#: depth is 16-bit millimetres.
SEMANTIC_MODES = ("L", "P", "I", "I;16", "I;16B", "I;16L")
DEPTH_MODES = ("I;16", "I;16B", "I;16L", "I")
#: Below this largest depth (millimetres) a depth map is not plausible: metres stored as integers, or
#: an 8-bit map scaled up, would put every point within a metre of the camera.
MIN_PLAUSIBLE_DEPTH_MM = 1000
_IMAGE_ERRORS = (OSError, ValueError, SyntaxError, Image.DecompressionBombError)


def _layer_problem(kind: str, mode: str) -> str | None:
    """Why an image of PIL ``mode`` cannot be layer ``kind`` (from its header alone), or None."""
    if kind == "semantics" and mode not in SEMANTIC_MODES:
        return f"semantic map must be a single-channel PNG of class ids, got mode {mode}"
    if kind == "depth" and mode not in DEPTH_MODES:
        bits = " (8-bit)" if mode in ("L", "P", "1") else ""
        return f"depth map must be a 16-bit single-channel PNG (uint16 millimetres), got mode {mode}{bits}"
    return None


def _deep_problem(kind: str, im: Image.Image, class_ids: set[int]) -> str | None:
    """Decode the whole image (a truncated file fails here, not at its header) and check its values."""
    im.load()
    if kind == "semantics":
        a = np.asarray(im)
        ids = set(np.unique(a).tolist())
        if max(ids, default=0) > 255:
            return "semantic ids above 255"
        unknown = sorted(ids - class_ids)
        if unknown and len(unknown) == len(ids):
            return f"no pixel holds a class id of the sequence's classes (ids found: {unknown[:8]})"
    if kind == "depth":
        a = np.asarray(im).astype(np.int64)
        top = int(a.max(initial=0))
        if 0 < top < MIN_PLAUSIBLE_DEPTH_MM:
            return (f"depth values reach only {top} mm: depth maps are uint16 millimetres (0 = unknown); "
                    "metres or an 8-bit map scaled up?")
    return None


def validate_sequence(seq: Sequence, check_images: bool = True, max_problems: int = 50,
                      deep: bool = False, detections: bool = True) -> list[Problem]:
    """Check the files a sequence refers to. Returns problems (file, message); empty when valid.

    Always: files exist; with ``check_images``, each image's header (size, and the layer's mode:
    semantics single-channel, depth 16-bit). With ``deep`` (``pavemap info``, the run's check up front), also
    decode every image in full and check values: semantic ids from the class table, depth in a plausible range.
    ``detections``: also read ``detections.jsonl``.
    """
    assert seq.root is not None
    problems: list[Problem] = []
    class_ids = {c.id for c in seq.classes}

    for f in seq.frames:
        def add(file: str | Path, msg: str, frame: int = f.index) -> bool:
            problems.append(Problem(str(file), msg, frame))
            return len(problems) >= max_problems

        for cam, v in f.views.items():
            c = seq.cameras[cam]
            for kind, rel in (("image", v.image), ("semantics", v.semantics), ("depth", v.depth)):
                if rel is None:
                    continue
                p = seq.root / rel
                if not _is_file(p):
                    if add(p, f"{kind} missing (frame {f.index}, camera {cam})"):
                        return problems
                    continue
                if not check_images:
                    continue
                try:
                    with Image.open(p) as im:
                        size = im.size
                        why = _layer_problem(kind, im.mode)
                        if why is None and size == (c.width, c.height) and deep:
                            why = _deep_problem(kind, im, class_ids)
                except _IMAGE_ERRORS as e:
                    if add(p, f"unreadable {kind} ({e})"):
                        return problems
                    continue
                if size != (c.width, c.height):
                    why = f"{kind} is {size[0]}x{size[1]}, camera {cam} is {c.width}x{c.height}"
                if why and add(p, why):
                    return problems
    det_file = seq.root / DETECTIONS_FILE
    if detections and det_file.is_file():
        try:
            read_detections(det_file)
        except SequenceError as e:
            problems.append(Problem(e.file, e.problem))
    return problems


def _is_file(p: Path) -> bool:
    try:
        return p.is_file()
    except OSError:  # a name too long for the file system: not a file we can read either
        return False


# ---------------------------------------------------------------------------- layers


def load_rgb(path: str | os.PathLike) -> np.ndarray:
    """(H, W, 3) uint8; grey images become 3 channels, alpha is dropped, EXIF orientation ignored (the
    intrinsics describe the sensor's pixels). OpenCV decodes (a 1241 x 376 PNG in 9.6 ms, PIL 14.3 ms); what it
    cannot read goes to PIL, which reads it or names the problem."""
    # only existing files: OpenCV prints its own warning for a missing one before PIL names the problem
    im = cv2.imread(os.fspath(path), cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION) if _is_file(Path(path)) \
        else None
    if im is not None:
        return cv2.cvtColor(im, cv2.COLOR_BGR2RGB)
    try:
        with Image.open(path) as im:
            return np.asarray(im.convert("RGB"))
    except _IMAGE_ERRORS as e:
        raise SequenceError(path, f"cannot read image ({e})") from None


def load_gray(path: str | os.PathLike, width: int | None = None) -> np.ndarray:
    """(H, W) uint8 grey, ``width`` px wide (area average, aspect kept) when given; :func:`load_rgb` decodes."""
    im = cv2.imread(os.fspath(path), cv2.IMREAD_GRAYSCALE | cv2.IMREAD_IGNORE_ORIENTATION) \
        if _is_file(Path(path)) else None
    im = im if im is not None else cv2.cvtColor(load_rgb(path), cv2.COLOR_RGB2GRAY)  # PIL, or the problem named
    if width is not None and width != im.shape[1]:
        im = cv2.resize(im, (width, max(8, round(im.shape[0] * width / im.shape[1]))), interpolation=cv2.INTER_AREA)
    return im


def load_semantics(path: str | os.PathLike) -> np.ndarray:
    """(H, W) uint8 class ids."""
    try:
        with Image.open(path) as im:
            why = _layer_problem("semantics", im.mode)
            if why:
                raise SequenceError(path, why)
            a = np.asarray(im)
    except SequenceError:
        raise
    except _IMAGE_ERRORS as e:
        raise SequenceError(path, f"cannot read semantic map ({e})") from None
    if a.dtype != np.uint8:
        if a.max(initial=0) > 255 or a.min(initial=0) < 0:
            raise SequenceError(path, "semantic ids outside 0..255")
        a = a.astype(np.uint8)
    return a


def load_depth(path: str | os.PathLike) -> np.ndarray:
    """(H, W) float32 metres, 0 = unknown (stored as uint16 millimetres)."""
    try:
        with Image.open(path) as im:
            why = _layer_problem("depth", im.mode)
            if why:
                raise SequenceError(path, why)
            a = np.asarray(im)
    except SequenceError:
        raise
    except _IMAGE_ERRORS as e:
        raise SequenceError(path, f"cannot read depth map ({e})") from None
    return a.astype(np.float32) / 1000.0


def save_depth(path: str | os.PathLike, depth_m: np.ndarray) -> None:
    mm = np.clip(np.nan_to_num(depth_m, nan=0.0, posinf=0.0) * 1000.0 + 0.5, 0, 65535).astype(np.uint16)
    Image.fromarray(mm).save(path)


# ---------------------------------------------------------------------------- detections


def read_detections(path: str | os.PathLike) -> list[Detection]:
    """Read ``detections.jsonl``. A line that breaks the schema (:class:`pavemap.io.schema.DetectionJson`)
    or names an unknown class id raises SequenceError naming the file, the line and the field.

    Values that are well-formed but unusable (boxes outside the image, NaN confidence, a
    frame that does not exist) are the filter's business: it skips and counts them.
    """
    from pavemap.io.schema import issues_text, parse_detection  # pydantic loads here, as in sequence_from_dict

    path = Path(path)
    dets: list[Detection] = []
    try:
        data = path.read_bytes()
    except OSError as e:
        raise SequenceError(path, f"cannot read detections ({e.strerror or e})") from None
    for ln, line in enumerate(decode_utf8(data, path).split("\n"), 1):
        if not line.strip():
            continue
        rec, issues = parse_detection(parse_json(line, path, f"line {ln}: "))
        if rec is None:
            raise SequenceError(path, f"line {ln}: not a detection record: {issues_text(issues)}")
        if not 0 <= rec.cls < NUM_DEFECT_CLASSES:
            raise SequenceError(path, f"line {ln}: cls: unknown class id {rec.cls} (valid: 0 D00, 1 D10, 2 D20, 3 D40)")
        dets.append(Detection(rec.frame, rec.camera, tuple(rec.box), rec.cls, rec.conf))  # type: ignore[arg-type]
    return dets


def write_detections(path: str | os.PathLike, detections: list[Detection], extra: list[dict] | None = None) -> Path:
    """Write detections as JSONL (atomically). ``extra`` adds per-line fields (e.g. a backend's ids)."""
    from pavemap.io.atomic import atomic_write_text
    from pavemap.io.owned import note_written

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
    written = atomic_write_text(path, "\n".join(out) + ("\n" if out else ""))
    note_written(written)  # into a sequence folder pavemap wrote: one of its files now
    return written
