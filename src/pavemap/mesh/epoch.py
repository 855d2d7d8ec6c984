"""One epoch of stage-1 training: a random share of the training pixels in batches of ``pixels_per_step``.

The full-grid heights the march uses are refreshed every ``height_refresh_steps`` steps; with pose refinement
the colours are re-baked on the current poses every ``pose_bake_every`` steps; a non-finite step is skipped
until ``max_bad_steps`` come in a row.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from tqdm.auto import tqdm

from pavemap.errors import PavemapError
from pavemap.geometry import surface_bounds
from pavemap.mesh.bake import bake_into
from pavemap.mesh.config import MeshConfig
from pavemap.mesh.evaluate import psnr
from pavemap.mesh.pose import corrected_poses
from pavemap.mesh.step import Fit, NonFiniteStepError, train_step


def posed(fit: Fit) -> torch.Tensor:
    """(V, 4, 4) training poses with the current corrections."""
    return corrected_poses(fit.pool.T, None if fit.poses is None else fit.poses.view_delta())


@dataclass
class Loop:
    """The step schedule of a run and its progress bar; ``bad`` counts consecutive non-finite steps."""

    n_epoch: int  # pixels visited per epoch
    steps: int  # steps per epoch
    total: int  # steps of the whole run
    bar: tqdm
    bad: int = 0


def run_epoch(fit: Fit, loop: Loop, epoch: int, gen: torch.Generator, fill: float) -> dict[str, float]:
    """One pass over a random ``loop.n_epoch`` of the training pixels; the summed step losses."""
    cfg, model = fit.cfg, fit.model
    perm = torch.randperm(len(fit.pool), generator=gen)[:loop.n_epoch].to(fit.pool.view.device)
    sums: dict[str, float] = {"loss": 0.0, "rgb": 0.0, "sem": 0.0, "depth": 0.0, "smooth": 0.0, "se": 0.0, "n": 0}
    cache = bounds = None
    for step in range(loop.steps):
        if cache is None or step % cfg.height_refresh_steps == 0:
            cache = model.dense_heights(fill).reshape(-1)
            bounds = surface_bounds(model.field(cache), torch.float32)
        gstep = epoch * loop.steps + step
        if fit.poses is not None and rebake_due(gstep, loop.total, cfg):
            # Poses align to the consensus texture of all views: re-baked on the current poses, it is the
            # multi-view average, whereas Adam's per-vertex colours fit single pixels and leave a wide pose loss.
            bake_into(model, fit.pool, posed(fit), fill, cfg.max_dist, cfg.bake_fill_sigma)
        b = perm[step * cfg.pixels_per_step:(step + 1) * cfg.pixels_per_step]
        if b.numel() == 0:
            continue
        try:
            out = train_step(fit, b, cache, bounds, gstep / loop.total)
        except NonFiniteStepError as e:  # skip the step; give up only when it keeps happening
            loop.bad += 1
            if loop.bad >= cfg.max_bad_steps:
                raise PavemapError(f"training diverged: {loop.bad} consecutive non-finite {e.what} "
                                   f"(epoch {epoch + 1})") from None
            loop.bar.update(1)
            continue
        loop.bar.update(1)
        if out is None:
            continue
        loop.bad = 0
        for k in sums:
            sums[k] += out[k]
        if step % 4 == 0:
            loop.bar.set_postfix(epoch=f"{epoch + 1}/{cfg.epochs}", loss=f"{out['loss']:.4f}",
                                 psnr=f"{psnr(sums['se'] / max(1, sums['n'])):.2f}")
    return sums


def rebake_due(gstep: int, total: int, cfg: MeshConfig) -> bool:
    """With pose refinement: whether step ``gstep`` re-bakes the colours (every ``pose_bake_every`` steps
    once the poses move)."""
    return gstep >= cfg.pose_warmup * total and (gstep - math.ceil(cfg.pose_warmup * total)) % cfg.pose_bake_every == 0
