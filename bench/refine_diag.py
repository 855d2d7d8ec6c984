"""Why stage-1 training does not move a wrong height (issue 47, item 1): the height gradient per loss term.

On a synthetic drive without depth, the surface is set to the truth plus a known offset (-10 .. +10 cm) and
the gradient of each training loss term (``pavemap.mesh.step``: rgb, sem, depth from the ground points, smooth)
with respect to a global height offset is measured on a fixed batch of pixels, in two cases:

- ``truth texture``: the colours baked on the true surface, then the surface shifted (no re-bake): the
  texture is right and only the geometry is wrong;
- ``re-baked``: the surface shifted, then the colours baked on it (what a run does: ``bake_init`` bakes
  onto whatever surface the closed form gives before the first step).

The global offset's gradient is the gradient on the height MLP's last bias (heights = MLP + z_base). A
positive offset must give a positive gradient (descent lowers the surface). Also the global offset
the multi-view consistency of :mod:`pavemap.mesh.refine` asks of the same surfaces
(a shifted surface should get minus its offset).

    python bench/refine_diag.py --drive DIR [--preset kitti] [--batch 65536]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))

from pavemap.io.sequence import read_sequence  # noqa: E402
from pavemap.io.truth import read_truth_height  # noqa: E402
from pavemap.mesh import MeshConfig  # noqa: E402
from pavemap.mesh.bake import bake_into  # noqa: E402
from pavemap.mesh.epoch import posed as _posed  # noqa: E402
from pavemap.mesh.geometry import add_point_depth, find_geometry  # noqa: E402
from pavemap.mesh.init_surface import initial_heights  # noqa: E402
from pavemap.mesh.render import view_rays  # noqa: E402
from pavemap.mesh.setup import prepare  # noqa: E402
from pavemap.mesh.step import _losses, forward_rays  # noqa: E402
from pavemap.mesh.train import _make_fit, _Run  # noqa: E402

OFFSETS = (-0.10, -0.05, 0.0, 0.05, 0.10)


def setup(drive: Path, preset: str):  # noqa: ANN201
    """The fit of a run on ``drive`` (as ``reconstruct`` builds it), its fill height and the true heights (Nv,)."""
    import time

    seq = read_sequence(drive)
    cfg = MeshConfig.preset(preset)
    cfg.resume, cfg.epochs, cfg.device = False, 1, "cpu"
    cfg.render_scale = float(os.environ.get("REFINE_SCALE", cfg.render_scale))
    notes: list[str] = []
    data = prepare(seq, cfg, torch.device("cpu"), notes.append)
    geo = find_geometry(seq, data, cfg, notes.append)
    if geo.observable and cfg.ground_points_use in ("depth", "both"):
        data.pool, data.use_depth = add_point_depth(data.pool, geo.gp, cfg.render_scale, seq.cameras), True
    z = initial_heights(data.pool, data.grid, data.traj, geo.cam_h, cfg, ground_points=geo.init_points(cfg))
    run = _Run(data, float(np.median(z)), geo.cam_h, geo, torch.device("cpu"), notes, time.perf_counter(),
               torch.Generator().manual_seed(1))
    fit = _make_fit(run, cfg, z, seq.name, notes.append)
    truth = read_truth_height(seq.root)
    zt, inside = truth.height_at(torch.from_numpy(data.grid.vertex_xy()))
    zt = torch.where(inside, zt, torch.as_tensor(z, dtype=zt.dtype)).float()
    return fit, run, zt, torch.as_tensor(z, dtype=torch.float32)


def term_gradients(fit, run, batch: torch.Tensor) -> dict[str, float]:  # noqa: ANN001
    """d(term)/d(global height offset) for each loss term on the pixels ``batch``."""
    model, pool, cfg = fit.model, fit.pool, fit.cfg
    bias = model.height_mlp.mlp1[-1].bias
    cache = model.dense_heights(run.fill).reshape(-1)
    o, d = view_rays(pool.K, pool.T, pool.view[batch], pool.uv[batch])
    out = {}
    for name in ("rgb", "sem", "depth", "smooth", "loss"):
        fw = forward_rays(model, cache, None, o, d, cfg.max_dist, height_rays=None)
        gt = pool.rgb[batch][fw.rows].float() / 255.0
        terms = _losses(fit, batch, fw, d, gt)
        weight = {"rgb": cfg.w_rgb, "sem": cfg.w_sem, "depth": cfg.w_depth, "smooth": cfg.w_smooth}.get(name, 1.0)
        model.zero_grad(set_to_none=True)
        if terms[name].requires_grad:
            (weight * terms[name]).backward()
        out[name] = float(bias.grad) if bias.grad is not None else 0.0
    return out


def consistency_step(fit, run, z: torch.Tensor) -> float:  # noqa: ANN001
    """The global offset (m) the multi-view consistency asks of heights ``z`` (Nv,) (its Gauss-Newton solve)."""
    from pavemap.mesh.refine import pool_images
    from pavemap.mesh.refine_solve import consistency_scan

    rgb, mask = pool_images(fit.pool)
    xy = torch.from_numpy(run.data.grid.vertex_xy())
    return consistency_scan(rgb, mask, fit.pool.K, _posed(fit), xy, z, fit.cfg.resolution, fit.cfg.max_dist)[0]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--drive", type=Path, required=True)
    ap.add_argument("--preset", default="kitti")
    ap.add_argument("--batch", type=int, default=65536)
    ap.add_argument("--results", type=Path, default=None, help="merge the table into this JSON (key diagnosis)")
    a = ap.parse_args()
    torch.set_num_threads(1)
    fit, run, zt, z_closed = setup(a.drive, a.preset)
    gen = torch.Generator().manual_seed(0)
    batch = torch.randperm(len(fit.pool), generator=gen)[:a.batch]
    rows = []
    for rebake in (False, True):
        for off in OFFSETS:
            with torch.no_grad():
                fit.model.z_base.copy_(zt + (off if rebake else 0.0))
                bake_into(fit.model, fit.pool, _posed(fit), run.fill, fit.cfg.max_dist, fit.cfg.bake_fill_sigma,
                          semantics=fit.use_sem)
                fit.model.z_base.copy_(zt + off)
            g = term_gradients(fit, run, batch)
            row = {"offset_m": off, "texture": "re-baked" if rebake else "truth", **{f"d_{k}": g[k] for k in g}}
            row["consistency_offset_m"] = consistency_step(fit, run, zt + off)
            rows.append(row)
            print(json.dumps(row), flush=True)
    if a.results is not None:
        from pavemap.io.atomic import atomic_write_json

        res = json.loads(a.results.read_text()) if a.results.is_file() else {}
        res["diagnosis"] = {"drive": str(a.drive), "preset": a.preset, "batch_pixels": int(batch.numel()),
                            "closed_form_bias_m": round(float((z_closed - zt).mean()), 4), "rows": rows}
        atomic_write_json(a.results, res)


if __name__ == "__main__":
    main()
