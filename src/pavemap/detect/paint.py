"""Lane paint under a detection box: the stage-2 rule against detections on road markings.

A real crack detector fires on lane lines (a painted line looks like a longitudinal crack). Paint
does not move between frames, so multi-frame fusion would *confirm* those boxes; the road filter
keeps them too (paint is road). The rule here measures how much of a box is paint and the filter
drops the box when paint spans it (:func:`box_paint_cover` ≥ ``FilterConfig.tau_paint``).

Where paint is: the view's semantic map when it has a paint class (``lane_marking``, ``lane
marking``, ``crosswalk``, ``road_marking``: the synthetic world writes ``lane_marking``), otherwise
the image: bright, unsaturated (white) or saturated yellow pixels in elongated runs, relative to the
view's own brightness (a shadowed line is still brighter than its asphalt).
"""

from __future__ import annotations

import numpy as np

from pavemap.io.sequence import SequenceError, load_rgb, load_semantics
from pavemap.types import Sequence

PAINT_CLASS_NAMES = ("lane_marking", "lane marking", "crosswalk", "road_marking", "road marking")


def paint_class_ids(seq: Sequence) -> list[int]:
    """Ids of the sequence's classes that mark paint."""
    return [c.id for c in seq.classes if c.name.lower() in PAINT_CLASS_NAMES]


def paint_from_image(rgb: np.ndarray) -> np.ndarray:
    """(H, W) bool paint guess from an (H, W, 3) uint8 image: white or yellow, brighter than the road.

    White: saturation < 0.25 and value above the 90th percentile of the lower half (the road there);
    yellow: hue 35-70°, saturation > 0.35, value > 0.45. Runs thinner than 2 px or shorter than 6 px
    along either axis are dropped (noise, not a line).
    """
    from scipy import ndimage

    x = rgb.astype(np.float32) / 255.0
    mx, mn = x.max(-1), x.min(-1)
    sat = np.where(mx > 0, (mx - mn) / np.maximum(mx, 1e-6), 0.0)
    low = mx[mx.shape[0] // 2 :]
    bright = max(0.55, float(np.percentile(low, 90)))
    white = (sat < 0.25) & (mx > bright)
    r, g, b = x[..., 0], x[..., 1], x[..., 2]
    yellow = (sat > 0.35) & (mx > 0.45) & (r >= b) & (g >= b) & (np.abs(r - g) < 0.35 * mx)
    paint = ndimage.binary_opening(white | yellow, structure=np.ones((2, 2), bool))
    lab, n = ndimage.label(paint)
    if n == 0:
        return paint
    keep = np.zeros(n + 1, dtype=bool)
    for k, sl in enumerate(ndimage.find_objects(lab), start=1):
        if sl is not None and max(sl[0].stop - sl[0].start, sl[1].stop - sl[1].start) >= 6:
            keep[k] = True
    return keep[lab]


def box_paint_cover(paint: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """(n,) how fully paint spans each box (n, 4: x1, y1, x2, y2 pixels): min(share of its rows, share of its
    columns) holding a ``paint`` (H, W) pixel.

    A box drawn around a piece of lane line has the line running corner to corner or edge to edge: every
    row and every column hits paint (≈ 1). A crack crossing a line, or beside it, has the line in a
    third of its columns or rows at most. (The paint *area* share does not separate them: a thin line
    fills 5-30 % of its own box, as much as a line crossing a wide crack box.)
    """
    H, W = paint.shape
    b = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    out = np.zeros(len(b))
    for i, (x1, y1, x2, y2) in enumerate(b):  # pixel centres inside the box, as boxes.box_ratio
        c0, r0 = int(np.clip(np.ceil(x1), 0, W - 1)), int(np.clip(np.ceil(y1), 0, H - 1))
        c1, r1 = int(np.clip(np.floor(x2) + 1, c0 + 1, W)), int(np.clip(np.floor(y2) + 1, r0 + 1, H))
        sub = paint[r0:r1, c0:c1]
        out[i] = min(sub.any(1).mean(), sub.any(0).mean())
    return out


class PaintSource:
    """Paint masks of a sequence's views (semantics where they mark paint, else the image), per view."""

    def __init__(self, seq: Sequence):
        self.seq = seq
        ids = paint_class_ids(seq)
        self.lut = np.zeros(256, dtype=bool)
        self.lut[ids] = True
        self.semantic = bool(ids)
        self.used_image = 0
        self._frames: dict | None = None

    def mask(self, frame: int, camera: str) -> np.ndarray | None:
        root = self.seq.root
        if self._frames is None:
            self._frames = self.seq.frame_by_index()
        view = self._frames[frame].views[camera]
        if root is None:
            return None
        if self.semantic and view.semantics:
            return self.lut[load_semantics(root / view.semantics)]
        try:
            rgb = load_rgb(root / view.image)
        except SequenceError:  # the image is not at hand (a detections-only check): no paint rule here
            return None
        self.used_image += 1
        return paint_from_image(rgb)

    def cover(self, frame: int, camera: str, boxes: np.ndarray) -> np.ndarray:
        """(n,) :func:`box_paint_cover` of each box in that view; NaN when the view's pixels are not at hand."""
        m = self.mask(frame, camera)
        if m is None:
            return np.full(len(boxes), np.nan)
        return box_paint_cover(m, boxes)


__all__ = ["PAINT_CLASS_NAMES", "PaintSource", "box_paint_cover", "mark_paint_and_ego", "paint_class_ids",
           "paint_from_image"]


def mark_paint_and_ego(seq: Sequence, boxes_by_view: dict[tuple[int, str], tuple[list[int], np.ndarray]],
                       reasons: list[str], tau_paint: float) -> np.ndarray:
    """Stage-2 rules after the road filter, in place on ``reasons``: "ego" for a box mostly (> 50 %) on the
    camera's ego mask (the bonnet), "paint" for a box that paint spans (cover ≥ ``tau_paint``; 1 = off).

    ``boxes_by_view``: (frame, camera) → (detection indices, boxes (n, 4)) of detections still "ok".
    Returns the paint cover per detection (len(reasons),), NaN where not measured.
    """
    from pavemap.detect.boxes import box_ratio
    from pavemap.io.egomask import load_ego_mask

    cover = np.full(len(reasons), np.nan)
    ego = {n: load_ego_mask(seq.root, c.ego_mask, c.width, c.height) for n, c in seq.cameras.items()}
    source = PaintSource(seq) if tau_paint < 1.0 else None
    for (frame, camera), (idx, boxes) in boxes_by_view.items():
        if ego.get(camera) is not None:
            on_ego = box_ratio(ego[camera], boxes) > 0.5
            for i in np.asarray(idx)[on_ego]:
                reasons[i] = "ego"
        if source is not None:
            cover[idx] = source.cover(frame, camera, boxes)
            for i, c in zip(idx, cover[idx], strict=True):
                if reasons[i] == "ok" and c >= tau_paint:
                    reasons[i] = "paint"
    return cover
