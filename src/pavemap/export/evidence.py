"""Evidence photos: for each defect the best camera view, cropped around the box with the box drawn.

An inspector verifies a mapped defect from a photo, so every defect gets ``evidence/<id>.jpg`` (the
path goes into ``inst.extra["evidence"]``) or, when no view can show it, ``inst.extra["evidence_note"]``
saying why (no kept detection fused into it, image missing or unreadable).

Which view is best (:func:`view_scores`, vectorised over all candidate detections): the one a person
would choose to judge the defect — close, looking down on it rather than grazing along the road,
confidently detected, and not cut by the image border. Per candidate detection::

    score = 0.4 * exp(-distance_m / 10 m)          # closer is sharper and larger
          + 0.3 * cos(incidence)                    # ray from the camera to the surface hit vs the vertical
          + 0.3 * conf                              # the detector's own confidence
          - 0.2 * (box touches the image border)    # a truncated view shows part of the defect

``cos(incidence)`` is ``|dz| / |hit - camera centre|`` from ``hit_xyz`` and the view's pose (1 straight
down, 0 grazing). Without a surface hit (no distance, no ray) the box's vertical position stands in
for both: a box low in a forward camera's image is near the vehicle and seen more steeply.
"""

from __future__ import annotations

import logging
import os
import re
from pathlib import Path

import numpy as np

from pavemap.errors import PavemapError, SequenceError
from pavemap.io.atomic import atomic_path
from pavemap.types import DefectInstance, Sequence

log = logging.getLogger("pavemap")

EVIDENCE_DIR = "evidence"
BOX_COLOUR = (255, 0, 255)  # magenta: rare on roads, so the drawn box stands out (and tests can find it)
MARGIN = 0.5  # context around the box, as a fraction of the box size on each side
MIN_CROP_PX = 96  # smallest crop side in source pixels (a 10 px box still shows its surroundings)
OUT_MIN_SIDE = 240  # crops are scaled so their short side is at least this (small far-away boxes)
OUT_MAX_SIDE = 720
QUALITY = 85
TRIES = 3  # candidate views tried per defect when an image cannot be read
_NAME = re.compile(r"^(\d+)\.jpg$")


def view_scores(distance: np.ndarray, cos_inc: np.ndarray, conf: np.ndarray, rel_bottom: np.ndarray,
                at_border: np.ndarray) -> np.ndarray:
    """Score of each candidate view (higher is better; module docstring).

    All (N,) float64 except ``at_border`` (N,) bool; ``distance`` and ``cos_inc`` are nan where
    unknown; ``rel_bottom`` is the box's bottom edge / image height in [0, 1].
    """
    near = np.where(np.isfinite(distance), np.exp(-np.nan_to_num(distance, nan=0.0) / 10.0), 0.5 * rel_bottom)
    steep = np.where(np.isfinite(cos_inc), np.nan_to_num(cos_inc, nan=0.0), 0.5 * rel_bottom)
    c = np.clip(np.nan_to_num(conf, nan=0.0), 0.0, 1.0)
    return 0.4 * near + 0.3 * np.clip(steep, 0.0, 1.0) + 0.3 * c - 0.2 * at_border.astype(np.float64)


def _candidates(seq: Sequence, detections: list[dict]) -> dict[int, list[dict]]:
    """Kept detections fused into an instance, grouped by instance id, best view first."""
    frames = seq.frame_by_index()
    recs, cams, boxes, sizes = [], [], [], []
    for r in detections:
        inst, box = r.get("instance"), r.get("box")
        if not r.get("kept") or inst is None or not box or any(v is None for v in box):
            continue
        f = frames.get(int(r["frame"]))
        view = f.views.get(str(r["camera"])) if f is not None else None
        cam = seq.cameras.get(str(r["camera"]))
        if view is None or cam is None:
            continue
        recs.append(r)
        cams.append(view.T_world_cam[:3, 3])
        boxes.append(box)
        sizes.append((cam.width, cam.height))
    if not recs:
        return {}
    b = np.asarray(boxes, dtype=np.float64)  # (N, 4) x1 y1 x2 y2, full-resolution pixels
    wh = np.asarray(sizes, dtype=np.float64)  # (N, 2)
    hit = np.array([r.get("hit_xyz") or [np.nan] * 3 for r in recs], dtype=np.float64)  # (N, 3)
    ray = hit - np.asarray(cams, dtype=np.float64)
    cos_inc = np.abs(ray[:, 2]) / np.maximum(np.linalg.norm(ray, axis=1), 1e-9)
    dist = np.array([np.nan if r.get("distance_m") is None else r["distance_m"] for r in recs], dtype=np.float64)
    conf = np.array([np.nan if r.get("conf") is None else r["conf"] for r in recs], dtype=np.float64)
    border = (b[:, 0] <= 1) | (b[:, 1] <= 1) | (b[:, 2] >= wh[:, 0] - 2) | (b[:, 3] >= wh[:, 1] - 2)
    score = view_scores(dist, cos_inc, conf, np.clip(b[:, 3] / wh[:, 1], 0.0, 1.0), border)
    out: dict[int, list[dict]] = {}
    for k in np.argsort(-score, kind="stable"):
        out.setdefault(int(recs[k]["instance"]), []).append({**recs[k], "score": float(score[k])})
    return out


def crop_with_box(image: np.ndarray, box: tuple[float, float, float, float], label: str = "") -> np.ndarray:
    """Crop (H, W, 3) uint8 around ``box`` (x1, y1, x2, y2 image pixels) with a margin and draw the box.

    Returns (h, w, 3) uint8, scaled so the short side is at least ``OUT_MIN_SIDE`` (at most ``OUT_MAX_SIDE``
    on the long side). ``label`` is written in the top-left corner.
    """
    from PIL import Image, ImageDraw

    H, W = image.shape[:2]
    x1, y1, x2, y2 = (float(v) for v in box)
    cx, cy = 0.5 * (x1 + x2), 0.5 * (y1 + y2)
    half_w = max((x2 - x1) * (0.5 + MARGIN), MIN_CROP_PX / 2)
    half_h = max((y2 - y1) * (0.5 + MARGIN), MIN_CROP_PX / 2)
    c0, c1 = int(max(0, np.floor(cx - half_w))), int(min(W, np.ceil(cx + half_w)))
    r0, r1 = int(max(0, np.floor(cy - half_h))), int(min(H, np.ceil(cy + half_h)))
    c1, r1 = max(c1, c0 + 1), max(r1, r0 + 1)
    im = Image.fromarray(np.ascontiguousarray(image[r0:r1, c0:c1]))
    s = max(OUT_MIN_SIDE / min(im.size), 1.0)
    s = min(s, OUT_MAX_SIDE / max(im.size)) if max(im.size) * s > OUT_MAX_SIDE else s
    if abs(s - 1.0) > 1e-6:
        im = im.resize((max(1, round(im.size[0] * s)), max(1, round(im.size[1] * s))), Image.BILINEAR)
    draw = ImageDraw.Draw(im)
    lw = max(3, round(min(im.size) / 80))
    bx = [(x1 - c0) * s, (y1 - r0) * s, (x2 - c0) * s, (y2 - r0) * s]
    # drawn just outside the box, so a thin crack's box does not hide the crack itself
    draw.rectangle([min(bx[0], bx[2]) - lw, min(bx[1], bx[3]) - lw, max(bx[0], bx[2]) + lw,
                    max(bx[1], bx[3]) + lw], outline=BOX_COLOUR, width=lw)
    if label:
        draw.rectangle([0, 0, 8 + 7 * len(label), 16], fill=(0, 0, 0))
        draw.text((4, 2), label, fill=(255, 255, 255))
    return np.asarray(im.convert("RGB"))


def _load_view(seq: Sequence, frames: dict, cand: dict) -> tuple[np.ndarray, list[float]] | str:
    """The view's image and the box in its pixels, or why it cannot be used."""
    from pavemap.io.sequence import load_rgb

    view = frames[int(cand["frame"])].views[str(cand["camera"])]
    cam = seq.cameras[str(cand["camera"])]
    try:
        img = load_rgb(seq.path(view.image))
    except (SequenceError, ValueError, OSError) as e:
        return f"image {view.image} unreadable ({e})"
    # boxes are in the camera's full-resolution pixels; an image stored smaller scales them
    sx, sy = img.shape[1] / max(cam.width, 1), img.shape[0] / max(cam.height, 1)
    return img, [cand["box"][0] * sx, cand["box"][1] * sy, cand["box"][2] * sx, cand["box"][3] * sy]


def _remove_stale(folder: Path, keep: set[int]) -> None:
    """Delete ``<id>.jpg`` of an earlier run that has no defect of that id now (ours by name)."""
    if not folder.is_dir():
        return
    for p in folder.iterdir():
        m = _NAME.match(p.name)
        if m and int(m.group(1)) not in keep and p.is_file():
            p.unlink(missing_ok=True)


def write_evidence(out_dir: str | os.PathLike, instances: list[DefectInstance], detections: list[dict] | None,
                   seq: Sequence | None) -> dict[str, Path]:
    """Write ``evidence/<id>.jpg`` for each instance and record the path (or a note) in ``inst.extra``.

    ``detections``: the fusion records (``FusionResult.detections``: kept, instance, box, frame, camera,
    conf, distance_m, hit_xyz). Returns ``{"evidence/<id>.jpg": path}``. Never raises for a missing or
    unreadable image: the defect gets ``evidence_note`` instead. A write error (OSError) propagates.
    """
    out = Path(out_dir) / EVIDENCE_DIR
    _remove_stale(out, {int(i.id) for i in instances})
    for inst in instances:
        inst.extra.pop("evidence", None)
        inst.extra.pop("evidence_note", None)
    if not instances:
        return {}
    if seq is None or seq.root is None:
        for inst in instances:
            inst.extra["evidence_note"] = "no camera images available to this export"
        return {}
    cands = _candidates(seq, detections or [])
    frames = seq.frame_by_index()
    paths: dict[str, Path] = {}
    for inst in instances:
        views = cands.get(int(inst.id), [])
        if not views:
            inst.extra["evidence_note"] = "no usable view: no kept detection was fused into this defect"
            continue
        why = []
        for cand in views[:TRIES]:
            got = _load_view(seq, frames, cand)
            if isinstance(got, str):
                why.append(got)
                continue
            crop = crop_with_box(got[0], got[1], f"#{inst.id} {inst.code} f{int(cand['frame'])}")
            rel = f"{EVIDENCE_DIR}/{int(inst.id)}.jpg"
            from PIL import Image

            try:
                with atomic_path(Path(out_dir) / rel) as tmp:
                    Image.fromarray(crop).save(tmp, format="JPEG", quality=QUALITY)
            except OSError as e:  # read-only or full disk: name the file, no traceback
                raise PavemapError(f"{Path(out_dir) / rel}: cannot write the evidence photo "
                                   f"({e.strerror or e})") from None
            paths[rel] = Path(out_dir) / rel
            inst.extra["evidence"] = rel
            break
        else:
            inst.extra["evidence_note"] = "no usable view: " + "; ".join(why)
            log.warning("defect %d: %s", inst.id, inst.extra["evidence_note"])
    return paths


__all__ = ["BOX_COLOUR", "EVIDENCE_DIR", "crop_with_box", "view_scores", "write_evidence"]
