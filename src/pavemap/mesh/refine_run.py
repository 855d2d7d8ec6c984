"""The photometric refinement and the consistency self-check inside a stage-1 run (``mesh.refine``,
``mesh.consistency_check``; docs/refine.md)."""

from __future__ import annotations

import time
from collections.abc import Callable

import torch

from pavemap.mesh.config import MeshConfig
from pavemap.mesh.data import PixelPool
from pavemap.mesh.model import RoadMeshModel
from pavemap.mesh.refine import pool_images
from pavemap.mesh.refine_solve import COARSE, consistency_scan

COARSE_ROUNDS = 3
FINE = tuple(round(0.005 * k, 3) for k in range(-6, 7))  # m: +-3 cm in 5 mm around the coarse scan's offset


@torch.no_grad()
def refine_offset(model: RoadMeshModel, pool: PixelPool, T: torch.Tensor, cfg: MeshConfig) -> dict:
    """Move the model's surface by the global offset at which the training views agree best (coarse scans on
    images blurred by 2 px, then a fine one at 1 px); returns what it did (``offset_m``, ``seconds``, and
    ``no_minimum`` true when it left the surface where it was).

    A coarse scan whose best offset is the edge of its range has found no minimum, only a slope: the views
    agree better and better the farther the surface goes. On the real nuScenes clips (SfM poses) that walked
    the surface 31 and 63 cm down, the camera 1.71 and 2.13 m above it (docs/refine.md): the consistency
    there is no evidence of a height, so the surface keeps the closed form's."""
    t = time.perf_counter()
    rgb, mask = pool_images(pool)
    xy = torch.from_numpy(model.grid.vertex_xy())
    total = last = 0.0
    # the coarse scan again while it still moves the surface by more than its step (a surface off by more than
    # ~10 cm moved only part of the way in one scan, measured on tests/mesh_scene.py), then the fine one
    for sigma, offsets in ((2.0, COARSE),) * COARSE_ROUNDS + ((1.0, FINE),):
        if sigma == 2.0 and total != 0.0 and abs(last) < 0.02:
            continue
        z = model.current_heights().double().cpu()
        off, _ = consistency_scan(rgb, mask, pool.K, T, xy, z, cfg.resolution, cfg.max_dist, sigma=sigma,
                                  offsets=offsets)
        if off is None:
            break
        if offsets is COARSE and abs(off) >= max(COARSE) - 1e-9:
            model.z_base.add_(-total)
            return {"offset_m": 0.0, "no_minimum": True, "seconds": round(time.perf_counter() - t, 2)}
        model.z_base.add_(float(off))
        total, last = total + float(off), float(off)
    return {"offset_m": round(total, 4), "no_minimum": False, "seconds": round(time.perf_counter() - t, 2)}


@torch.no_grad()
def consistency_metrics(model: RoadMeshModel, pool: PixelPool, T: torch.Tensor, cfg: MeshConfig) -> dict:
    """The self-check: the global offset (m) the multi-view consistency asks of the final surface and whether
    it is beyond ``mesh.check_max_consistency_m`` (``flagged``)."""
    t = time.perf_counter()
    rgb, mask = pool_images(pool)
    xy = torch.from_numpy(model.grid.vertex_xy())
    off, _ = consistency_scan(rgb, mask, pool.K, T, xy, model.current_heights().double().cpu(), cfg.resolution,
                              cfg.max_dist)
    flagged = off is not None and abs(off) > cfg.check_max_consistency_m
    return {"offset_m": None if off is None else round(off, 4), "flagged": flagged,
            "seconds": round(time.perf_counter() - t, 2)}


def record(model: RoadMeshModel, pool: PixelPool, T: torch.Tensor, cfg: MeshConfig, refined: dict | None,
           warn: Callable[[str], None], metrics: dict) -> None:
    """Into ``metrics``: what the refinement did (``refine``) and the self-check (``consistency``), warning
    when the views agree best more than ``mesh.check_max_consistency_m`` off the surface."""
    if refined is not None:
        metrics["refine"] = refined
        if refined.get("no_minimum"):
            warn("mesh.refine left the surface as the closed form made it: the views' consistency has no "
                 f"minimum within +-{100 * max(COARSE):.0f} cm of it (no evidence of the height)")
    if cfg.consistency_check:
        metrics["consistency"] = c = consistency_metrics(model, pool, T, cfg)
        if c["flagged"]:
            warn(f"surface not trustworthy: the views agree best {100 * c['offset_m']:+.1f} cm off it "
                 "(multi-view consistency)")
