"""Stage-1 training: fit heights, colours and semantics of the BEV mesh to the frames (SPEC §1).

The driver :func:`reconstruct` runs, in order: the data (:mod:`pavemap.mesh.setup`), the geometry without
depth (ground points and camera height, :mod:`pavemap.mesh.geometry`), the initial surface
(:mod:`pavemap.mesh.init_surface`), the model and optimizer, resuming (:mod:`pavemap.mesh.checkpoint`),
the pose alignment (:mod:`pavemap.mesh.pose`), the epochs of optimisation steps
(:func:`pavemap.mesh.step.train_step`, each sampling ``pixels_per_step`` pixels from all training views;
the full-grid heights the march uses are refreshed every ``height_refresh_steps`` steps), the final bake,
the evaluation (:mod:`pavemap.mesh.evaluate`) and the geometry self-check (``metrics["geometry"]``).
"""

from __future__ import annotations

import dataclasses
import math
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from tqdm.auto import tqdm

from pavemap.device import resolve_device
from pavemap.errors import PavemapError
from pavemap.mesh.bake import bake_into, march_pool
from pavemap.mesh.checkpoint import CHECKPOINT, Resumed, resume, save_checkpoint
from pavemap.mesh.config import MeshConfig
from pavemap.mesh.data import PixelPool
from pavemap.mesh.epoch import Loop, posed, run_epoch
from pavemap.mesh.evaluate import evaluate_pool, psnr, stage_metrics
from pavemap.mesh.geometry import (
    Geometry,
    add_point_depth,
    anchor_correction,
    find_geometry,
    height_observed,
    point_vertices,
    self_check,
)
from pavemap.mesh.init_surface import initial_heights
from pavemap.mesh.model import RoadMesh, RoadMeshModel, to_road_mesh
from pavemap.mesh.pose import PoseCorrections, align_poses, corrected_poses, rig_corrections, rig_groups
from pavemap.mesh.setup import TrainData, Warn, prepare, visible_pixels
from pavemap.mesh.step import Fit, make_optimizer
from pavemap.types import Sequence

LOSS_KEYS = ("loss", "rgb", "sem", "depth", "smooth")


def reconstruct_piece(seq: Sequence, out_dir: Path | None, config: MeshConfig, progress: bool = True,
                      heldout_frames: set[int] | None = None) -> tuple[RoadMesh, dict]:
    """Stage 1 on a sequence in one piece: the mesh and its metrics (:func:`pavemap.mesh.segments.reconstruct`
    decides first whether a long drive is cut into segments, each of which comes here)."""
    from threadpoolctl import threadpool_limits

    threads_before = torch.get_num_threads()
    if config.threads:
        torch.set_num_threads(int(config.threads))
    try:
        with threadpool_limits(limits=config.blas_threads or None, user_api="blas"):
            return _reconstruct(seq, out_dir, config, progress, heldout_frames)
    finally:
        torch.set_num_threads(threads_before)


@dataclass
class _Run:
    """One run's state besides the model: its data, where training resumes from, and the warnings."""

    data: TrainData
    fill: float  # height off the crop (never used as surface)
    cam_h: float
    geo: Geometry
    device: torch.device
    notes: list[str]
    t_start: float
    gen: torch.Generator  # the order in which each epoch visits the pixels
    n_groups: int = 0  # pose correction groups (frames or views)
    done: Resumed = dataclasses.field(default_factory=lambda: Resumed(0, [], 0.0))
    align_log: list[dict] = dataclasses.field(default_factory=list)
    moving_share: float = 0.0  # training pixels left out as moving objects (_drop_moving)
    all_pixels: PixelPool | None = None  # the pool before _drop_moving (what the texture check compares)
    samples: np.ndarray | None = None  # (N, 3) the height measurements (_samples)
    exposure: torch.Tensor | None = None  # (V, 2) the training views' gain and offset (final bake)
    init_hits: list | None = None  # the visible-pixel march on the initial surface, for the initial bake
    relief_state: dict | None = None  # the initial relief fit's point weights, for the kerb refit
    refined: dict | None = None  # what the photometric refinement did (mesh.refine)

    def warn(self, msg: str) -> None:
        self.notes.append(msg)
        warnings.warn(msg, stacklevel=3)


def _reconstruct(seq: Sequence, out_dir: Path | None, cfg: MeshConfig, progress: bool,
                 heldout_frames: set[int] | None) -> tuple[RoadMesh, dict]:
    from pavemap.mesh.outputs import write_outputs

    t_start = time.perf_counter()
    cfg.validate()
    device = resolve_device(cfg.device)
    notes: list[str] = []

    def warn(msg: str) -> None:
        notes.append(msg)
        warnings.warn(msg, stacklevel=3)

    data = prepare(seq, cfg, device, warn, heldout_frames)
    geo = find_geometry(seq, data, cfg, warn)
    if geo.observable and cfg.ground_points_use in ("depth", "both"):
        data.pool, data.use_depth = add_point_depth(data.pool, geo.gp, cfg.render_scale, seq.cameras), True
    relief_state: dict = {}
    z_vertices = initial_heights(data.pool, data.grid, data.traj, geo.cam_h, cfg, ground_points=geo.init_points(cfg),
                                 relief_state=relief_state)
    run = _Run(data, float(np.median(z_vertices)), geo.cam_h, geo, device, notes, t_start,
               torch.Generator().manual_seed(cfg.seed + 1), relief_state=relief_state)
    fit = _make_fit(run, cfg, z_vertices, seq.name, warn)
    if out_dir is not None and cfg.resume and fit.opt is not None and (Path(out_dir) / CHECKPOINT).is_file():
        _resume(fit, run, Path(out_dir), warn)
    if fit.poses is not None and cfg.pose_align_iters > 0 and run.done.epoch == 0:
        delta0, run.align_log = _align_stage(fit, run)
        fit.poses.set(delta0)
    if cfg.moving_cutoff > 0:
        _drop_moving(fit, run)
    if cfg.bake_init and run.done.epoch == 0:
        bake_into(fit.model, fit.pool, posed(fit), run.fill, cfg.max_dist, cfg.bake_fill_sigma, hits=run.init_hits,
                  semantics=fit.use_sem, ground=_ground(fit, run))
        if _kerb_refit(fit, run) and cfg.epochs > 0:
            bake_into(fit.model, fit.pool, posed(fit), run.fill, cfg.max_dist, cfg.bake_fill_sigma,
                      semantics=fit.use_sem, ground=_ground(fit, run))
    run.init_hits = None  # freed before training
    if cfg.refine and run.done.epoch == 0:
        from pavemap.mesh.refine_run import refine_offset

        run.refined = refine_offset(fit.model, fit.pool, posed(fit), cfg)
    run.relief_state = None
    history, schedule = _train(fit, run, out_dir, progress)
    mesh, metrics = _finish(fit, run, seq, history, schedule)
    if out_dir is not None:
        write_outputs(Path(out_dir), mesh, metrics, data.classes)
    return mesh, metrics


@torch.no_grad()
def _kerb_refit(fit: Fit, run: _Run) -> bool:
    """Fit the initial relief again, free to step where the baked classes change between road and not
    (``mesh.kerb_steps``); True if the surface was replaced. A vertex is off the road where at least
    ``mesh.kerb_off_share`` of its pixels' votes say so: the vertex at the foot of a kerb's face also collects
    the face's pixels, and a bare majority put the step a cell early on the road."""
    cfg, data, m = fit.cfg, run.data, fit.model
    if not (cfg.kerb_steps and fit.use_sem and cfg.init_relief == "road" and m.sem.shape[1]
            and run.relief_state and "points" in run.relief_state):  # the relief was fitted to measurements
        return False
    is_road = torch.tensor([c.road for c in data.classes])
    sem = m.sem.detach().cpu()
    p_off = torch.softmax(sem, dim=1)[:, ~is_road].sum(dim=1)
    side = (p_off < cfg.kerb_off_share).numpy().astype(np.int64)
    side[~(sem != 0).any(dim=1).numpy()] = -1  # no labelled pixel reached it
    other = torch.tensor([c.movable or c.sky for c in data.classes])
    side[other[sem.argmax(dim=1)].numpy()] = -1  # a car is no kerb: its points must not get an island of its own
    if len(np.unique(side[side >= 0])) < 2:
        return False
    # the points come from relief_state: the same ones the first fit used
    z = initial_heights(data.pool, data.grid, data.traj, run.cam_h, cfg, vertex_side=side,
                        relief_state=run.relief_state)
    m.z_base.copy_(torch.as_tensor(z, dtype=m.z_base.dtype, device=m.z_base.device))
    return True


def _drop_moving(fit: Fit, run: _Run) -> None:
    """Leave out of training the pixels that disagree with the road the other views see (moving objects)."""
    from pavemap.mesh.bake import static_pixels

    m = fit.model
    keep = static_pixels(m.field(m.dense_heights(run.fill)), fit.pool, posed(fit), fit.cfg.max_dist,
                         fit.cfg.moving_cutoff, fill_sigma=fit.cfg.bake_fill_sigma, blob_px=fit.cfg.moving_blob_px)
    dropped = int((~keep).sum())
    run.moving_share = dropped / max(1, len(fit.pool))
    if dropped:
        run.all_pixels, fit.pool = fit.pool, fit.pool.subset(keep)
        if run.moving_share > 0.01:
            run.warn(f"{100 * run.moving_share:.1f} % of the training pixels disagree with the road the other views "
                     "see (moving vehicles, or a surface still far off) and are left out of the texture and the "
                     "height fit")


def _finish(fit: Fit, run: _Run, seq: Sequence, history: list[dict], schedule: dict[str, int]
            ) -> tuple[RoadMesh, dict]:
    """The final bake, the mesh, and the run's metrics."""
    cfg, data = fit.cfg, run.data
    if cfg.anchor_to_points and cfg.epochs > 0:  # without training the surface is the points' fit already
        _anchor(fit, run)
    seen, mesh, texture = _final_bake(fit, run)
    metrics = {**stage_metrics(fit, data, mesh, run.fill, _eval_delta(fit, data), seen, seq.root, run.exposure),
               "device": str(run.device), "epochs": cfg.epochs, **schedule, "camera_height_init": run.cam_h,
               "moving_pixel_share": round(run.moving_share, 5), **texture}
    run.samples = _samples(fit, run)
    mesh.samples = run.samples
    mesh.observed = _observed(fit, run, seen)
    s = mesh.surface
    metrics["geometry"] = self_check(run.geo, data.grid.spec, s.heights.detach().cpu().numpy(),
                                     s.valid.cpu().numpy(), mesh.observed.cpu().numpy(), cfg, run.warn)
    if cfg.refine or cfg.consistency_check:
        from pavemap.mesh.refine_run import record

        record(fit.model, fit.pool, posed(fit), cfg, run.refined, run.warn, metrics)
    metrics.update(history=history, warnings=run.notes, config=cfg.to_dict())
    if fit.poses is not None:
        metrics["pose_alignment"] = run.align_log
    metrics["seconds"] = run.done.seconds + time.perf_counter() - run.t_start
    if not torch.isfinite(mesh.surface.heights[mesh.surface.valid]).all():
        raise PavemapError("reconstruction produced non-finite heights")
    return mesh, metrics


def _ground(fit: Fit, run: _Run) -> torch.Tensor | None:
    """(C,) bool: the semantic channels whose pixels colour the texture (``mesh.bake_ground_only``), or None."""
    classes = run.data.classes
    if not fit.cfg.bake_ground_only or not classes:
        return None
    g = torch.tensor([c.ground for c in classes], dtype=torch.bool)
    return None if bool(g.all()) else g


def _final_bake(fit: Fit, run: _Run) -> tuple[torch.Tensor | None, RoadMesh, dict]:
    """The final bake (``seen`` (Nv,) bool or None without it), the mesh, and the texture check's metrics
    (:mod:`pavemap.mesh.texture_check`; ``{"texture_check": ...}`` or empty) on one march of the pixels, freed
    before the held-out evaluation."""
    cfg, data = fit.cfg, run.data
    seen, hits, texture = None, None, {}
    check = cfg.texture_check and cfg.bake_final
    if cfg.bake_final:
        if check and run.all_pixels is None:  # the check compares the pixels the bake used: one march for both
            m = fit.model
            hits = march_pool(m.field(m.dense_heights(run.fill)), fit.pool, posed(fit), cfg.max_dist)
        seen, run.exposure = bake_into(fit.model, fit.pool, posed(fit), run.fill, cfg.max_dist,
                                       cfg.bake_fill_sigma, sharpen_iters=cfg.bake_sharpen_iters,
                                       exposure_rounds=cfg.exposure_rounds, hits=hits, ground=_ground(fit, run))
    mesh = to_road_mesh(fit.model, data.class_ids, data.use_sem)
    if check:
        from pavemap.mesh.texture_check import check_model_texture

        pixels = fit.pool if run.all_pixels is None else run.all_pixels  # those _drop_moving left out too
        mesh.contested, texture["texture_check"] = check_model_texture(
            fit.model, mesh, data.classes, pixels, posed(fit), run.fill, cfg, run.exposure, run.warn, hits)
    return seen, mesh, texture


@torch.no_grad()
def _anchor(fit: Fit, run: _Run) -> None:
    """Move the trained surface back onto its height measurements (:func:`pavemap.mesh.geometry.anchor_correction`):
    the depth pixels where the sequence has depth, otherwise the fitted ground points (never the held-out ones,
    which check the result)."""
    from pavemap.mesh.init_surface import depth_points

    m, gp = fit.model, run.geo.gp
    if run.geo.source == "depth" and fit.pool.depth is not None:
        points = depth_points(fit.pool, n_max=200000, seed=fit.cfg.seed)
    else:
        points = gp.points if gp is not None and gp.observable else None
    h = m.dense_heights(float("nan")).cpu().numpy()
    corr = anchor_correction(points, run.data.grid.spec, h, run.data.grid.vertex_xy(), run.data.traj[:, :2])
    if corr is not None:
        m.z_base.add_(torch.as_tensor(corr, dtype=m.z_base.dtype, device=m.z_base.device))


def _observed(fit: Fit, run: _Run, seen: torch.Tensor | None) -> torch.Tensor:
    """(ny, nx) bool: the vertices whose height was measured (:func:`pavemap.mesh.geometry.height_observed`:
    a ground point or depth sample within ``mesh.observed_radius_m``) and that a training pixel reaches
    (``seen`` (Nv,), from the final bake; without a final bake, a bake's support on the final surface)."""
    m = fit.model
    if seen is None:
        from pavemap.mesh.bake import bake_colours

        _, support, _ = bake_colours(m.field(m.dense_heights(run.fill)), fit.pool, posed(fit), fit.cfg.max_dist,
                                     fit.cfg.bake_fill_sigma)
        seen = support.reshape(-1)[m.vertex_flat_ids] > 0
    pix = m.dense(seen.to(torch.bool), fill=False).cpu().numpy()
    spec = run.data.grid.spec
    measured = height_observed(spec, fit.cfg.observed_radius_m, run.samples)
    return torch.from_numpy((pix | point_vertices(run.geo.gp, spec)) & measured & run.data.grid.valid)


def _samples(fit: Fit, run: _Run) -> np.ndarray | None:
    """(N, 3) float32 the run's height measurements: every ground point (fit and held out) and up to 200,000
    depth pixels cast on their poses (:attr:`pavemap.mesh.model.RoadMesh.samples`); None without any."""
    from pavemap.mesh.init_surface import depth_points

    parts = [g.points for g in (run.geo.gp, run.geo.check_gp) if g is not None and len(g)]
    sensed = None
    if run.geo.source == "depth" and fit.pool.depth is not None:  # measured depth (not the points cast into it)
        sensed = depth_points(fit.pool, n_max=200000, seed=fit.cfg.seed)
    parts += [sensed] if sensed is not None else []
    return np.concatenate(parts).astype(np.float32) if parts else None


def _make_fit(run: _Run, cfg: MeshConfig, z_vertices: np.ndarray, seq_name: str, warn: Warn) -> Fit:
    """The model on the initial surface, the pose corrections, the optimizer, and the visible pixels."""
    data = run.data
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(cfg.seed)
        gen = torch.Generator().manual_seed(cfg.seed)
        model = RoadMeshModel(data.grid, len(data.classes), cfg.pe_levels, cfg.hidden, z_vertices, generator=gen)
    model.to(run.device)
    group, arm, run.n_groups = rig_groups(data.pool.keys, data.pool.T, cfg.pose_per)
    poses = PoseCorrections(group, arm, run.n_groups, run.device) if cfg.pose_refine else None
    # without epochs there is nothing to step (and torch's first optimizer imports torch._dynamo: ~2 s)
    opt, params = make_optimizer(model, poses, cfg) if cfg.epochs > 0 else (None, [])
    # the initial bake sees what this march saw unless poses or the pool change in between
    reuse = cfg.bake_init and poses is None and cfg.moving_cutoff <= 0
    data.pool, run.init_hits = visible_pixels(model, data.pool, run.fill, cfg.max_dist, seq_name, warn,
                                              keep_hits=reuse, use_sem=data.use_sem)
    depth_on = data.use_depth and data.pool.depth is not None and cfg.w_depth > 0
    return Fit(cfg, model, opt, params, poses, data.pool, data.use_sem, depth_on)


def _resume(fit: Fit, run: _Run, out_dir: Path, warn: Warn) -> None:
    """Continue from ``out_dir/checkpoint.pt`` when it belongs to this run."""
    got = resume(out_dir, fit.model, fit.opt, run.gen, run.n_groups, run.device, cfg=fit.cfg)
    if got is None:
        warn("checkpoint in the output folder does not match this run; starting afresh")
        return
    run.done, delta = got
    run.init_hits = None  # the surface is the checkpoint's now
    if fit.poses is not None and delta is not None:
        fit.poses.set(delta)


def _eval_delta(fit: Fit, data: TrainData) -> torch.Tensor | None:
    """Pose corrections of the evaluation views: the training views' own, or interpolated for held-out frames."""
    from pavemap.mesh.pose import interpolate_corrections

    if fit.poses is None:
        return None
    delta = fit.poses.view_delta()
    return delta if data.epool.keys == fit.pool.keys else interpolate_corrections(fit.pool.keys, delta,
                                                                                  data.epool.keys)


def _align_stage(fit: Fit, run: _Run) -> tuple[torch.Tensor, list[dict]]:
    """Pose refinement before training: (G, 6) corrections from :func:`align_poses` on the initial surface,
    and per round the weighted residual cost before and after.

    With depth the initial surface was binned from points cast on the raw poses (blurred by their errors),
    so each round rebuilds it on the corrected poses (the next round aligns to the rebuilt one).
    """
    cfg, model, poses, pool = fit.cfg, fit.model, fit.poses, fit.pool
    delta = torch.zeros(poses.w.shape[0], 6, device=pool.T.device)
    log: list[dict] = []
    for rnd in range(cfg.pose_align_rounds):
        delta, costs = align_poses(model.field(model.dense_heights(run.fill)), pool, delta, cfg.max_dist,
                                   iters=cfg.pose_align_iters, per_view=cfg.pose_align_pixels_per_view,
                                   prior_sigma=(cfg.pose_prior_deg, cfg.pose_prior_m), group=poses.group,
                                   arm=poses.arm, seed=cfg.seed + rnd)
        if costs:
            log.append({"round": rnd + 1, "cost_first": costs[0], "cost_last": costs[-1]})
        if run.data.use_depth and cfg.init_from_depth:
            moved = dataclasses.replace(pool, T=corrected_poses(pool.T, rig_corrections(delta, poses.group, poses.arm)))
            z = initial_heights(moved, run.data.grid, run.data.traj, run.cam_h, cfg,
                                ground_points=run.geo.init_points(cfg))
            model.z_base.copy_(torch.as_tensor(z, dtype=model.z_base.dtype, device=model.z_base.device))
    return delta, log


def _train(fit: Fit, run: _Run, out_dir: Path | None, progress: bool) -> tuple[list[dict], dict[str, int]]:
    """The epochs from where the run resumes: steps, per-epoch evaluation and history, checkpoints.
    Returns the history and the schedule (``steps_per_epoch``, ``pixels_per_epoch``)."""
    cfg, model = fit.cfg, fit.model
    n_epoch = max(1, int(round(len(fit.pool) * min(cfg.pixel_fraction, 1.0))))
    steps = max(1, math.ceil(n_epoch / cfg.pixels_per_step))
    todo = (cfg.epochs - run.done.epoch) * steps
    bar = tqdm(total=todo, disable=not progress or todo <= 0, desc="mesh", unit="step", dynamic_ncols=True)
    loop = Loop(n_epoch, steps, max(1, cfg.epochs * steps), bar)
    history = run.done.history
    for epoch in range(run.done.epoch, cfg.epochs):
        t_ep = time.perf_counter()
        sums = run_epoch(fit, loop, epoch, run.gen, run.fill)
        ev = evaluate_pool(model, run.data.epool, model.dense_heights(run.fill), cfg.max_dist,
                           delta=_eval_delta(fit, run.data), max_pixels=100000,
                           generator=torch.Generator().manual_seed(cfg.seed + 2))
        history.append({
            "epoch": epoch + 1, **{f"l_{k}" if k != "loss" else k: sums[k] / steps for k in LOSS_KEYS},
            "train_psnr": psnr(sums["se"] / max(1, sums["n"])),
            "eval_psnr": ev["psnr"], "eval_sem_acc": ev["sem_acc"], "seconds": time.perf_counter() - t_ep,
        })
        bar.set_postfix(epoch=f"{epoch + 1}/{cfg.epochs}", loss=f"{history[-1]['loss']:.4f}",
                        psnr=f"{ev['psnr']:.2f}")
        if out_dir is not None:
            save_checkpoint(Path(out_dir) / CHECKPOINT, model, fit.opt,
                            None if fit.poses is None else fit.poses.delta(), epoch + 1, history, run.gen, cfg,
                            run.done.seconds + time.perf_counter() - run.t_start)
    bar.close()
    return history, {"steps_per_epoch": steps, "pixels_per_epoch": n_epoch}
