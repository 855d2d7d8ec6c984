"""From a sequence to what stage 1 trains on: the frame split, the pixel pools, the grid and its crop."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch

from pavemap.errors import PavemapError
from pavemap.mesh.bake import batch_hits, pool_hits
from pavemap.mesh.config import GroundConfig, MeshConfig
from pavemap.mesh.data import PixelPool, ScaledImages, build_pool, finite_views, split_frames
from pavemap.mesh.ground_points import GroundPoints, find_ground_points
from pavemap.mesh.init_surface import path_cuts, travel_direction
from pavemap.mesh.model import MeshGrid, RoadMeshModel, build_grid
from pavemap.types import SemanticClass, Sequence, View

Warn = Callable[[str], None]


MIN_POINTS = 50  # fewer triangulated ground points: geometry not observable


@dataclass
class TrainData:
    """The inputs of a stage-1 run.

    pool: the training pixels; epool: the evaluation pixels (the held-out views, or the training views
    when none is held out); grid: the vertex grid and its crop around ``traj`` (F, 3), the mean camera
    centre of every frame used; classes: the semantic classes trained (empty without semantic maps).
    """

    pool: PixelPool
    epool: PixelPool
    grid: MeshGrid
    traj: np.ndarray
    classes: list[SemanticClass]
    use_sem: bool
    use_depth: bool
    heldout: bool
    gp: GroundPoints | None = None  # the ground points triangulated from the training views (when asked)

    @property
    def class_ids(self) -> list[int]:
        return [c.id for c in self.classes]


def prepare(seq: Sequence, cfg: MeshConfig, device: torch.device, warn: Warn,
            heldout_frames: set[int] | None = None) -> TrainData:
    """Split the frames, drop views without a finite pose, build the grid and load the pixel pools.

    ``heldout_frames``: frame indices to hold out instead of every ``holdout_every``-th position (a segment of a
    long drive holds out the drive's own choice, so that no held-out frame trains a neighbouring segment)."""
    if not seq.frames:
        raise PavemapError(f"sequence {seq.name!r} has no frames")
    train_pos, held_pos = split_frames(len(seq.frames), cfg.holdout_every, cfg.frame_stride)
    if heldout_frames is not None:
        held_pos = [p for p, f in enumerate(seq.frames) if f.index in heldout_frames]
        held_set = set(held_pos)
        train_pos = [p for p in range(len(seq.frames)) if p not in held_set][::cfg.frame_stride]
    if cfg.holdout_every > 0 and not held_pos:
        warn("fewer than 2 frames: no frame held out; metrics are measured on the training views")
    train_views, dropped = finite_views(seq, train_pos)
    held_views, dropped_h = finite_views(seq, held_pos)
    if dropped + dropped_h:
        warn(f"{dropped + dropped_h} view(s) with a NaN/infinite pose skipped")
    if not train_views:
        raise PavemapError(f"sequence {seq.name!r}: no training view with a finite pose")
    use_sem = any(v.semantics for _, v in train_views)
    if not use_sem:
        warn("no semantic maps in the sequence: RGB-only reconstruction, road mask = mesh footprint")
    use_depth = any(v.depth for _, v in train_views)
    classes = list(seq.classes) if use_sem else []
    channel_lut = np.full(256, -1, dtype=np.int64)
    for ch, c in enumerate(classes):
        channel_lut[c.id] = ch

    grid, traj = trajectory_grid(train_views + held_views, cfg, warn)

    gp, images = None, None
    if cfg.ground_points == "always" or (cfg.ground_points == "auto" and not use_depth):
        # before the pool: the images the points decode are handed to it
        images = ScaledImages(seq, cfg.render_scale)
        gcfg = GroundConfig(prior_height=cfg.camera_height, scale=cfg.ground_points_scale,
                            max_corners=cfg.ground_points_corners)
        sub = frames_of(seq, {fi for fi, _ in train_views})  # held-out images must not shape the geometry
        gp = find_ground_points(sub, gcfg, min_points=MIN_POINTS, on_rgb=images.put)
    pool = build_pool(seq, train_views, cfg.render_scale, channel_lut, use_sem, use_depth, images).to(device)
    eval_views = held_views if held_views else train_views
    epool = build_pool(seq, eval_views, cfg.eval_scale, channel_lut, use_sem, use_depth).to(device)
    if use_sem and int((epool.channel >= 0).sum()) == 0:
        warn("held-out views carry no labelled pixels: semantic accuracy is undefined")
    return TrainData(pool, epool, grid, traj, classes, use_sem, use_depth, bool(held_views), gp)


def frames_of(seq: Sequence, frame_indices: set[int]) -> Sequence:
    """``seq`` restricted to the frames with these indices, in order."""
    return dataclasses.replace(seq, frames=[f for f in seq.frames if f.index in frame_indices])


def trajectory_grid(views: list[tuple[int, View]], cfg: MeshConfig, warn: Warn | None = None
                    ) -> tuple[MeshGrid, np.ndarray]:
    """The grid and its crop around the trajectory of ``views`` ((frame index, View) pairs) and the road the
    end frames look at; also the trajectory (F, 3), the mean camera centre of each frame in index order."""
    centres: dict[int, list[np.ndarray]] = {}
    for fi, v in views:
        centres.setdefault(fi, []).append(v.T_world_cam[:3, 3])
    traj = np.array([np.mean(centres[k], axis=0) for k in sorted(centres)])
    first, last = min(centres), max(centres)
    ends = [(0 if fi == first else -1, v) for fi, v in views if fi in (first, last)]
    pieces = path_pieces(traj[:, :2], sorted(centres), warn)
    grid = build_grid(pieces[0], cfg.resolution, cfg.crop_m,
                      [*pieces[1:], *view_paths(ends, traj[:, :2], cfg.view_range_m)])
    if grid.vertices < 3 or grid.faces == 0:
        raise PavemapError("the trajectory crop holds no triangle; check crop_m and resolution")
    return grid, traj


def path_pieces(traj_xy: np.ndarray, frame_ids: list[int], warn: Warn | None = None,
                min_gap_m: float = 5.0, gap_factor: float = 5.0) -> list[np.ndarray]:
    """The trajectory (F, 2) cut where consecutive frames lie more than ``max(min_gap_m, gap_factor x the
    median step)`` apart: dropped frames, or the passes of a long drive's segment. The crop follows each piece,
    not a straight line across the gap (road no camera drove past). Each gap is named through ``warn``."""
    t = np.asarray(traj_xy, dtype=np.float64).reshape(-1, 2)
    cuts = path_cuts(t, min_gap_m, gap_factor)
    step = np.linalg.norm(np.diff(t, axis=0), axis=1)
    if warn is not None:
        for c in cuts[np.diff(np.asarray(frame_ids))[cuts] == 1]:  # gaps between consecutive frame indices
            warn(f"frames {frame_ids[c]} and {frame_ids[c + 1]} lie {step[c]:.0f} m apart (dropped frames, or a "
                 "jump in the poses): the road between them is not reconstructed")
    return np.split(t, cuts + 1)


def view_paths(views: list[tuple[int, object]], traj_xy: np.ndarray, range_m: float) -> list[np.ndarray]:
    """(2, 2) segments from camera centres ``range_m`` along their horizontal view direction: the road the end
    frames see beyond the trajectory. views: (frame position 0 or -1 in the path, View) of the first and last
    frames. Only cameras looking out of the path's end (within 30 degrees of the direction of travel there,
    and within 60 degrees of horizontal) add one: a surround rig's side cameras (nuScenes' front-left and
    front-right look 55 degrees off the axis) see the road beside the path, which the crop already holds,
    and their axes would pull the mesh into the buildings."""
    out: list[np.ndarray] = []
    if range_m <= 0:
        return out
    traj_xy = np.asarray(traj_xy, dtype=np.float64).reshape(-1, 2)
    for end, v in views:
        c, axis = v.T_world_cam[:3, 3], v.T_world_cam[:3, 2]  # optical axis: camera +z (x right, y down)
        h = float(np.hypot(axis[0], axis[1]))
        if h <= 0.5:
            continue
        a = axis[:2] / h
        out_dir = travel_direction(traj_xy, end) if len(traj_xy) > 1 else None
        if out_dir is not None and float(a @ out_dir) < math.cos(math.radians(30.0)):
            continue
        out.append(np.array([c[:2], c[:2] + range_m * a]))
    return out


@torch.no_grad()
def visible_pixels(model: RoadMeshModel, pool: PixelPool, fill: float, max_dist: float, seq_name: str,
                   warn: Warn, batch: int = 262144, keep_hits: bool = False,
                   use_sem: bool = False) -> tuple[PixelPool, list | None]:
    """The pool without the pixels whose rays cannot meet the initial mesh (sky, far off the crop): they
    would fill batches with misses. Warns about views that see none of it; an error when no pixel is left.
    With ``keep_hits`` also the march itself (:func:`pavemap.mesh.bake.march_pool` of the returned pool on
    the initial surface from ``pool.T``), for a bake on that surface (11 s of a nuScenes-like drive's
    149 s 1-epoch stage 1 was the initial bake's repeat of this march); else None. ``use_sem``: the pool's
    road flags come from semantic maps, so a pool without a road pixel says that the maps label none."""
    no_road = use_sem and not bool(pool.road.any())
    labels = ("the semantic maps label no pixel as road (no pixel holds the id of a class with road: true in "
              "sequence.json's classes; wrong label maps or class table?)")
    hf0 = model.field(model.dense_heights(fill))
    keep = torch.zeros(len(pool), dtype=torch.bool, device=pool.view.device)
    hits = [] if keep_hits else None
    for sl, rows, vid, w in pool_hits(hf0, pool, pool.T, max_dist, batch):
        keep[sl.start + rows] = True
        if hits is not None:
            hits.append(batch_hits(pool, sl, rows, vid, w))
    seen = torch.bincount(pool.view[keep], minlength=len(pool.keys))
    blind = int((seen == 0).sum())
    if blind:
        # Usually not an error: a forward camera's nearest visible ground lies several metres ahead
        # (~7 m for KITTI's), so in the last frames it looks past the crop around the trajectory's end.
        names = [f"{pool.keys[i].frame}/{pool.keys[i].camera}" for i in (seen == 0).nonzero().squeeze(1).tolist()]
        warn(f"{blind} training view(s) see no part of the road mesh and are unused ({', '.join(names[:6])}"
             f"{', ...' if blind > 6 else ''}): pointing at the sky, or looking past the crop around the "
             "trajectory's ends")
    pool = pool.subset(keep)
    if len(pool) == 0:
        raise PavemapError(f"sequence {seq_name!r}: no training view sees the road area around the trajectory"
                           + (f"; {labels}" if no_road else ""))
    if use_sem and not bool(pool.road.any()):
        warn(labels if no_road else "no pixel of a road class is visible on the mesh area")
    if hits:  # their rows in the pool without the misses
        at = torch.cumsum(keep, 0) - 1
        hits = [h._replace(rows=at[h.rows]) for h in hits]
    return pool, hits
