"""Per-frame semantic masks for a sequence: label folders, a segmenter, or a warned fallback.

Three ways to get ``semantics/<camera>/<frame>.png`` (uint8 class ids) and the label table:

- :func:`attach_label_folder` — a folder of label PNGs plus a class map (preset or YAML,
  :mod:`pavemap.segment.labels`);
- :func:`segment_sequence` with a :class:`Segmenter`, e.g. the ultralytics semantic
  segmentation backend (:class:`pavemap.segment.yolo_seg.UltralyticsSegmenter`);
- :func:`corridor_semantics` — when neither is given: road = the trajectory corridor on
  the ground plane below each camera (below the horizon), everything else "terrain".
  It cannot see parked cars, curbs or intersections, so it warns loudly.
"""

from __future__ import annotations

import os
import warnings
from pathlib import Path
from typing import Protocol

import numpy as np
from PIL import Image

from pavemap.errors import PavemapError
from pavemap.io.atomic import atomic_path
from pavemap.io.sequence import SequenceError, load_rgb, load_semantics, write_sequence
from pavemap.segment.labels import PRESETS, LabelMap, find_label_file, load_label_map
from pavemap.types import SemanticClass, Sequence

__all__ = [
    "PRESETS",
    "LabelMap",
    "Segmenter",
    "attach_label_folder",
    "corridor_semantics",
    "load_label_map",
    "segment_sequence",
]


class Segmenter(Protocol):
    """Anything that turns RGB images into label maps of its own ``classes`` table."""

    classes: list[SemanticClass]

    def segment(self, images: list[np.ndarray]) -> list[np.ndarray]:
        """``images``: (H, W, 3) uint8 RGB each → (H, W) uint8 class ids each (same H, W)."""
        ...


def _save_labels(path: Path, labels: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        Image.fromarray(np.ascontiguousarray(labels.astype(np.uint8))).save(tmp, format="PNG")


def _semantics_rel(camera: str, frame: int) -> str:
    return f"semantics/{camera}/{frame:06d}.png"


def attach_label_folder(
    seq: Sequence, labels_dir: str | os.PathLike, class_map: str | os.PathLike | LabelMap = "pavemap",
    allow_missing: bool = False,
) -> Sequence:
    """Remap a folder of label PNGs into ``seq`` (semantics/…) and set its label table; rewrites sequence.json.

    Label files are looked up per view (see :func:`find_label_file`). A view without one
    raises (naming the paths tried) unless ``allow_missing``.
    """
    from tqdm import tqdm

    labels_dir = Path(labels_dir)
    if not labels_dir.is_dir():
        raise SequenceError(labels_dir, "labels folder not found")
    lm = class_map if isinstance(class_map, LabelMap) else load_label_map(class_map)
    valid = {c.id for c in lm.classes}
    n_cams = len(seq.cameras)
    views = [(f, cam, v) for f in seq.frames for cam, v in f.views.items()]
    found = 0
    for f, cam, v in tqdm(views, desc="labels", unit="img", disable=None):
        src = find_label_file(labels_dir, cam, f.index, v.image, n_cams)
        if src is None:
            if allow_missing:
                v.semantics = None
                continue
            raise SequenceError(
                labels_dir / cam / f"{f.index:06d}.png",
                f"no label PNG for frame {f.index} camera {cam} (also tried <image stem>.png"
                f"{' and the folder itself' if n_cams == 1 else ''})",
            )
        raw = load_semantics(src)
        c = seq.cameras[cam]
        if raw.shape != (c.height, c.width):
            raise SequenceError(
                src, f"label map is {raw.shape[1]}x{raw.shape[0]}, camera {cam} is {c.width}x{c.height}"
            )
        out = lm.remap(raw)
        bad = np.setdiff1d(np.unique(out), list(valid))
        if bad.size:
            src_vals = np.unique(raw[np.isin(out, bad)])
            raise SequenceError(src, f"label values {src_vals.tolist()[:10]} are not in class map {lm.name!r}")
        rel = _semantics_rel(cam, f.index)
        _save_labels(seq.path(rel), out)
        v.semantics = rel
        found += 1
    if found == 0:
        raise SequenceError(labels_dir, "no label PNG matched any view")
    seq.classes = list(lm.classes)
    write_sequence(seq)
    return seq


def _ego_id(classes: list[SemanticClass]) -> int | None:
    """The class the ego vehicle's pixels get: ``ego`` when the table has one, else its first movable class."""
    ego = next((c.id for c in classes if c.name == "ego"), None)
    return ego if ego is not None else next((c.id for c in classes if c.movable), None)


def segment_sequence(seq: Sequence, segmenter: Segmenter, batch: int = 8,
                     ego_masks: dict[str, np.ndarray | None] | None = None,
                     out_root: str | os.PathLike | None = None) -> Sequence:
    """Run a segmenter over every view; writes semantics/… and the segmenter's label table.

    ``ego_masks``: per camera, (H, W) bool True on the ego vehicle (bonnet): those pixels get the
    table's ``ego`` class (else its first movable class), never road. ``out_root``: write the label
    PNGs under this folder instead (a run folder; the views then point at them by absolute path) and
    leave the sequence folder and its sequence.json untouched.
    """
    from tqdm import tqdm

    root = Path(out_root) if out_root is not None else None
    ego_id = _ego_id(list(segmenter.classes))
    views = [(f, cam, v) for f in seq.frames for cam, v in f.views.items()]
    with tqdm(total=len(views), desc="segment", unit="img", disable=None) as bar:
        for i in range(0, len(views), batch):
            chunk = views[i : i + batch]
            imgs = [load_rgb(seq.path(v.image)) for _, _, v in chunk]
            labs = segmenter.segment(imgs)
            for (f, cam, v), img, lab in zip(chunk, imgs, labs, strict=True):
                if lab.shape != img.shape[:2]:
                    raise PavemapError(f"segmenter returned {lab.shape} labels for a {img.shape[:2]} image")
                ego = (ego_masks or {}).get(cam)
                if ego is not None and ego_id is not None and ego.shape == lab.shape:
                    lab = np.where(ego, np.uint8(ego_id), lab)
                rel = _semantics_rel(cam, f.index)
                target = seq.path(rel) if root is None else root / rel
                _save_labels(target, lab)
                v.semantics = rel if root is None else str(target.resolve())
            bar.update(len(chunk))
    seq.classes = list(segmenter.classes)
    if root is None:
        write_sequence(seq)
    return seq


def _segment_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distance of points ``p`` (N, 2) to the polyline of segments ``a``→``b`` (S, 2) each → (N,)."""
    ab = b - a  # (S, 2)
    L2 = np.maximum((ab**2).sum(1), 1e-12)
    best = np.full(len(p), np.inf)
    for s0 in range(0, len(a), 64):  # blocks of segments keep memory at N x 64
        sl = slice(s0, s0 + 64)
        ap = p[:, None, :] - a[None, sl]  # (N, s, 2)
        t = np.clip((ap * ab[None, sl]).sum(-1) / L2[None, sl], 0.0, 1.0)
        d = np.linalg.norm(ap - t[..., None] * ab[None, sl], axis=-1)
        best = np.minimum(best, d.min(1))
    return best


def corridor_semantics(
    seq: Sequence, half_width: float = 3.5, camera_height: float | None = None, max_range: float = 60.0,
    step: int = 4, extend: float = 20.0,
) -> Sequence:
    """Fallback road mask: pixels whose ray meets the ground within ``half_width`` of the driven path
    (extended by ``extend`` metres beyond the first and last frame).

    The ground is the plane ``camera_height`` below each camera (default: 1.65 m, KITTI's
    mount; or the height known from the import). Evaluated every ``step`` pixels and
    upsampled (the corridor edge is smooth). Writes the pavemap label table (road 0,
    terrain 4, sky 7). Warns: it cannot see vehicles, curbs or junctions.
    """
    from tqdm import tqdm

    msg = (
        f"no semantic masks or segmenter given for {seq.name!r}: using the trajectory-corridor fallback "
        f"(road = ground within {half_width} m of the driven path, below the horizon). It cannot reject "
        "detections on parked cars or off the carriageway; give --labels or a segmenter for real filtering."
    )
    warnings.warn(msg, UserWarning, stacklevel=2)
    lm = PRESETS["pavemap"]()
    road, other, sky = lm.id_of("road"), lm.id_of("terrain"), lm.id_of("sky")
    h = 1.65 if camera_height is None else float(camera_height)
    traj = seq.trajectory()[:, :2]  # (F, 2)
    # the road goes on beyond the first and last frames: extend the path along the end
    # headings (a single frame: along its cameras' mean viewing direction)
    if len(traj) == 1:
        fwd = np.mean([v.T_world_cam[:3, 2] for v in seq.frames[0].views.values()], axis=0)[:2]
        head = tail = fwd / max(np.linalg.norm(fwd), 1e-9)
    else:
        head = traj[-1] - traj[-2]
        tail = traj[1] - traj[0]
        head = head / max(np.linalg.norm(head), 1e-9)
        tail = tail / max(np.linalg.norm(tail), 1e-9)
    traj = np.vstack([traj[0] - extend * tail, traj, traj[-1] + extend * head])
    a, b = traj[:-1], traj[1:]
    for f in tqdm(seq.frames, desc="corridor masks", unit="frame", disable=None):
        for cam, v in f.views.items():
            c = seq.cameras[cam]
            us = np.arange(step // 2, c.width, step, dtype=np.float64)
            vs = np.arange(step // 2, c.height, step, dtype=np.float64)
            uu, vv = np.meshgrid(us, vs)
            rays = np.stack([uu, vv, np.ones_like(uu)], -1).reshape(-1, 3) @ np.linalg.inv(c.K).T
            R, t = v.T_world_cam[:3, :3], v.T_world_cam[:3, 3]
            d = rays @ R.T  # (N, 3) world directions
            ground_z = t[2] - h
            with np.errstate(divide="ignore", invalid="ignore"):
                lam = (ground_z - t[2]) / d[:, 2]
            down = (d[:, 2] < -1e-6) & (lam > 0)
            hit = t[None, :2] + lam[:, None] * d[:, :2]
            dist = np.full(len(d), np.inf)
            near = down & (np.linalg.norm(hit - t[None, :2], axis=1) < max_range)
            if near.any():
                dist[near] = _segment_distance(hit[near], a, b)
            lab = np.where(dist <= half_width, road, other).astype(np.uint8)
            lab[~down & (d[:, 2] > 0.05)] = sky  # well above the horizon
            lab = lab.reshape(len(vs), len(us))
            full = np.repeat(np.repeat(lab, step, 0), step, 1)[: c.height, : c.width]
            if full.shape != (c.height, c.width):  # width/height not a multiple of step
                full = np.pad(full, ((0, c.height - full.shape[0]), (0, c.width - full.shape[1])), mode="edge")
            rel = _semantics_rel(cam, f.index)
            _save_labels(seq.path(rel), full)
            v.semantics = rel
    seq.classes = list(lm.classes)
    write_sequence(seq)
    return seq
