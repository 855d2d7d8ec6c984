"""The views vote on the road: a segmenter's road pixels that most other views of the same ground call
something else are relabelled.

A Cityscapes network's mistakes depend on the view: a side camera looking down at a plain sidewalk from two
metres calls it road, the front camera sees the same sidewalk beside the kerb and calls it sidewalk; a building
base near the corner of one frame is road there and a wall in the next. The ground the views share is the same
ground, so each road-labelled pixel is cast onto the road surface, and where the views that see that cell of
the ground (``cell_m``) mostly give it another label, the pixel takes the cell's most voted other label.

- **The road surface** is the road under the drive's own path: the nearest camera centre minus its height over
  the road (``camera_height``, else each camera's ``height_m``), a ray's hit found in three fixed-point steps.
  A drive that climbs keeps its cells where they are (a flat plane under each camera put a point 20 m ahead on
  a 3 % grade 13 m too far).
- **One vote per view and cell** (its label shares in the cell): a near view covers a cell with hundreds of
  pixels, a far one with a few, and the near side camera is exactly the view that is wrong about a sidewalk.
- Only cells within ``max_range_m`` of a view vote or are judged there, only cells seen by at least
  ``min_views`` views are judged, movable classes (vehicles, the ego vehicle, what the plane check took
  off the road) and the sky do not vote. A drive is voted in windows of ``window_frames`` frames, so the memory
  does not grow with its length.

Thresholds chosen on the synthetic presets (``bench/segment_bench.py``, ``segment.json`` ``road_vote``).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from pavemap.segment.relabel_report import RelabelReport
from pavemap.types import Sequence

log = logging.getLogger(__name__)

_OFF = 2**20  # cell index offset: keys stay non-negative within +-200 km at 0.2 m cells
_CLASSES = 256  # label PNGs are uint8


@dataclass(frozen=True)
class RoadVoteConfig:
    """Settings of :func:`road_vote_sequence` (module docstring)."""

    cell_m: float = 0.2
    max_range_m: float = 30.0
    min_road_share: float = 0.6  # a cell whose views give road less than this share of their votes is not road
    min_views: int = 2
    vote_width: int = 320  # the voters' labels are read at this width (a cell is still several pixels at 30 m)
    judge_width: int = 640  # a judged view's cells are found at this width
    window_frames: int = 16  # frames judged together; the frames this far either side vote on them too


@dataclass
class RoadVoteReport(RelabelReport):
    """What :func:`road_vote_sequence` did, for the console and the bench."""

    voted: int = 0
    seconds: float = 0.0

    def describe(self) -> str:
        return (f"road vote: {self.voted}/{self.views} views judged by the views sharing their ground; "
                f"{self.share:.1%} of their road pixels relabelled (other views call that ground something else), "
                f"{self.seconds:.1f} s")


def ground_hits(K: np.ndarray, T_wc: np.ndarray, size: tuple[int, int], ground: np.ndarray, tree: cKDTree,
                max_range_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Where each pixel's ray meets the road under the path: (h*w, 2) float64 world xy and (h*w,) bool (hit
    within ``max_range_m``). ``K`` (3, 3) for the image ``size`` (w, h), ``T_wc`` (4, 4) camera to world,
    ``ground`` (M, 3) the road points under the path, ``tree`` a KD-tree of their xy."""
    w, h = size
    u, v = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    d = (np.stack([u, v, np.ones_like(u)], -1).reshape(-1, 3) @ np.linalg.inv(K).T) @ T_wc[:3, :3].T
    o = T_wc[:3, 3]
    down = d[:, 2] < -1e-6
    dz = np.where(down, d[:, 2], -1.0)
    z = np.full(len(d), ground[tree.query(o[:2])[1], 2])
    for _ in range(3):  # the hit's road height from the path point nearest it, then the hit again
        t = (z - o[2]) / dz
        xy = o[:2] + np.clip(t, 0, 1e4)[:, None] * d[:, :2]
        z = ground[tree.query(xy)[1], 2]
    t = (z - o[2]) / dz
    ok = down & (t > 0) & (t * np.linalg.norm(d, axis=1) <= max_range_m)
    return o[:2] + np.where(ok, t, 0.0)[:, None] * d[:, :2], ok


def cell_keys(xy: np.ndarray, cell_m: float) -> np.ndarray:
    """(N,) int64 key of the ground cell of each (N, 2) world xy."""
    ij = np.floor(xy / cell_m).astype(np.int64) + _OFF
    return ij[:, 0] * (2 * _OFF) + ij[:, 1]


def view_votes(keys: np.ndarray, labels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One view's vote: per (cell, label) key (K,) int64, the label's share (K,) float64 of the view's pixels
    in that cell (each cell the view sees sums to 1)."""
    ck, cell_inv, cell_n = np.unique(keys, return_inverse=True, return_counts=True)
    pk, inv = np.unique(keys * _CLASSES + labels, return_inverse=True)
    n = np.bincount(inv).astype(np.float64)
    return pk, n / cell_n[np.searchsorted(ck, pk // _CLASSES)]


def tally(votes: list[tuple[np.ndarray, np.ndarray]], road_lut: np.ndarray, min_views: int
          ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The cells' verdicts from the views' ``votes``: sorted cell keys (C,) int64, their road share (C,) float64
    (NaN where fewer than ``min_views`` views voted) and their most voted other label (C,) int64 (-1: none)."""
    pk = np.concatenate([k for k, _ in votes])
    sh = np.concatenate([s for _, s in votes])
    key, inv = np.unique(pk, return_inverse=True)
    w = np.bincount(inv, sh)
    cell, lab = key // _CLASSES, key % _CLASSES
    cells, cinv = np.unique(cell, return_inverse=True)
    total = np.bincount(cinv, w)
    road = np.bincount(cinv, w * road_lut[lab])
    share = np.where(total >= min_views - 1e-9, road / np.maximum(total, 1e-12), np.nan)
    other = np.full(len(cells), -1, dtype=np.int64)
    nr = ~road_lut[lab].astype(bool)
    order = np.lexsort((w[nr], cinv[nr]))  # by cell, then weight: the last of each cell is its top label
    c_sorted, l_sorted = cinv[nr][order], lab[nr][order]
    last = np.r_[c_sorted[1:] != c_sorted[:-1], True]
    other[c_sorted[last]] = l_sorted[last]
    return cells, share, other


def _k_at(seq: Sequence, cam_name: str, w: int, h: int) -> np.ndarray:
    """(3, 3) the camera's intrinsics for an image of ``w`` x ``h`` (per-axis factors, as the labels were resized)."""
    cam = seq.cameras[cam_name]
    K = cam.K.astype(np.float64).copy()
    K[0] *= w / cam.width
    K[1] *= h / cam.height
    return K


def _labels_at(labels: np.ndarray, width: int) -> np.ndarray:
    """(h, width) uint8 ``labels`` resized (nearest) to ``width``; as they are when already narrower."""
    from PIL import Image

    if labels.shape[1] <= width:
        return labels
    h = max(1, round(labels.shape[0] * width / labels.shape[1]))
    return np.asarray(Image.fromarray(labels).resize((width, h), Image.NEAREST))


def road_vote_sequence(seq: Sequence, camera_height: float | None = None,
                       cfg: RoadVoteConfig = RoadVoteConfig()) -> RoadVoteReport:
    """Relabel the road pixels of every posed view whose ground the other views mostly call something else
    (module docstring). ``camera_height``: the mount's height over the road (m); None: each camera's
    ``height_m`` (a camera with neither does not vote and is not judged). Label PNGs are rewritten in place
    (they are the segmenter's, just written)."""
    from pavemap.io.sequence import load_semantics
    from pavemap.segment import _save_labels

    t0 = time.perf_counter()
    rep = RoadVoteReport()
    road_lut, skip_lut = seq.class_lut("road"), seq.class_lut("movable") | seq.class_lut("sky")
    height = {c: camera_height if camera_height is not None else cam.height_m for c, cam in seq.cameras.items()}
    views = [(i, c, v) for i, f in enumerate(seq.frames) for c, v in f.views.items() if v.semantics]
    rep.views = len(views)
    rep.skipped = sorted({f"{c}: no camera height known" for _, c, _ in views if height.get(c) is None})
    views = [x for x in views if height.get(x[1]) is not None]
    if not views or not road_lut.any():
        rep.seconds = time.perf_counter() - t0
        return rep
    ground = np.array([v.T_world_cam[:3, 3] - [0.0, 0.0, height[c]] for _, c, v in views])
    tree = cKDTree(ground[:, :2])
    votes: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    n_frames, wf = len(seq.frames), cfg.window_frames
    for a in range(0, n_frames, wf):
        voters = [k for k, (i, _, _) in enumerate(views) if a - wf <= i < a + 2 * wf]
        for k in [k for k in votes if views[k][0] < a - wf]:
            del votes[k]
        for k in voters:
            if k not in votes:
                votes[k] = _vote_of(seq, views[k], ground, tree, skip_lut, cfg)
        cells, share, other = tally([votes[k] for k in voters], road_lut, cfg.min_views)
        for _, c, v in (x for x in views if a <= x[0] < a + wf):
            labels = load_semantics(seq.path(v.semantics))
            road = road_lut[labels]
            if not road.any():
                continue
            relabelled = _verdict(seq, c, v, labels, road, ground, tree, (cells, share, other), cfg)
            rep.voted += 1
            rep.road_px += int(road.sum())
            rep.relabelled_px += int((relabelled != labels).sum())
            if (relabelled != labels).any():
                _save_labels(seq.path(v.semantics), relabelled)
    rep.seconds = time.perf_counter() - t0
    return rep


def _verdict(seq: Sequence, c: str, v, labels: np.ndarray, road: np.ndarray, ground: np.ndarray, tree: cKDTree,
             cells_share_other: tuple[np.ndarray, np.ndarray, np.ndarray], cfg: RoadVoteConfig) -> np.ndarray:
    """(H, W) uint8 ``labels`` of one view with its ``road`` (H, W) pixels on cells that the views judged not
    road (share below ``cfg.min_road_share``) given the cell's most voted other label. The cells are found at
    ``cfg.judge_width`` (a pixel there is still a fraction of a cell at ``max_range_m``) and read at full size."""
    cells, share, other = cells_share_other
    h, w = labels.shape
    jw = min(w, cfg.judge_width)
    jh = max(1, round(h * jw / w))
    xy, ok = ground_hits(_k_at(seq, c, jw, jh), v.T_world_cam, (jw, jh), ground, tree, cfg.max_range_m)
    keys = cell_keys(xy, cfg.cell_m)
    pos = np.clip(np.searchsorted(cells, keys), 0, len(cells) - 1)
    bad = ok & (cells[pos] == keys) & (np.nan_to_num(share[pos], nan=1.0) < cfg.min_road_share) & (other[pos] >= 0)
    new = np.where(bad, other[pos], -1).reshape(jh, jw)
    rows, cols = (np.arange(h) + 0.5) * jh // h, (np.arange(w) + 0.5) * jw // w
    new = new[rows.astype(int)][:, cols.astype(int)]
    flip = road & (new >= 0)
    return np.where(flip, new, labels).astype(np.uint8)


def _vote_of(seq: Sequence, view: tuple, ground: np.ndarray, tree: cKDTree, skip_lut: np.ndarray,
             cfg: RoadVoteConfig) -> tuple[np.ndarray, np.ndarray]:
    """One view's (cell, label) votes (:func:`view_votes`) from its labels at ``cfg.vote_width``."""
    from pavemap.io.sequence import load_semantics

    _, c, v = view
    labels = _labels_at(load_semantics(seq.path(v.semantics)), cfg.vote_width)
    h, w = labels.shape
    xy, ok = ground_hits(_k_at(seq, c, w, h), v.T_world_cam, (w, h), ground, tree, cfg.max_range_m)
    lab = labels.ravel().astype(np.int64)
    use = ok & ~skip_lut[lab]
    return view_votes(cell_keys(xy[use], cfg.cell_m), lab[use])
