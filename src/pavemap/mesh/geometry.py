"""The road geometry of a stage-1 run when its views have no depth, and the run's self-check (issue 12).

Without a depth layer the images are the only height evidence. The ground points triangulated from the
training views (:func:`pavemap.mesh.ground_points.find_ground_points`, poses held fixed; run by
:func:`pavemap.mesh.setup.prepare` before the pixel pool, which takes the images they decode) are turned by
:func:`find_geometry` into the camera height above the road; the configured mount height ``mesh.camera_height``
is a prior with an uncertainty that the points override (and a warning when they disagree by more than
``mesh.camera_height_warn_frac``: a wrong mount height, or poses with a wrong scale). The points then
shape the initial surface and/or act as sparse depth (``mesh.ground_points_use``).

After training :func:`self_check` compares the final surface with the same points (median signed
residual, robust RMS), reports the height found vs the prior and the fraction of vertices observed, and
turns them into warnings: "surface not trustworthy: ..." or "geometry not observable: ...". Why a check
at all: a surface shifted in height with a re-baked texture still reproduces the training colours, so the
held-out PSNR cannot see a wrong height.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np
import torch

from pavemap.geometry.grid import GridSpec
from pavemap.geometry.road_height import camera_heights, height_estimate
from pavemap.geometry.triangulate import SurfaceCheck, check_height_field
from pavemap.mesh.config import MeshConfig
from pavemap.mesh.data import PixelPool
from pavemap.mesh.ground_points import GroundPoints, estimate_camera_height, view_scale_xy
from pavemap.mesh.init_surface import camera_height as searched_height
from pavemap.mesh.relief import ReliefFit
from pavemap.mesh.setup import MIN_POINTS, TrainData, Warn, frames_of
from pavemap.types import Camera, Sequence


@dataclass
class Geometry:
    """The height evidence of a run: ``gp`` the ground points (None when not computed), ``cam_h`` the camera
    height used (m, the mean camera centre of a frame above the road), ``source`` where it came from
    ("depth", "ground points", "plane search", "prior"), ``found`` / ``stderr`` the height the ground points
    give (None when not observable), ``per_camera`` {camera: found height, spread, frames}, ``notes`` the
    geometry warnings issued so far."""

    gp: GroundPoints | None
    cam_h: float
    source: str
    found: float | None = None
    stderr: float | None = None
    per_camera: dict[str, dict] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    check_gp: GroundPoints | None = None  # held-out ground points: the self-check's independent evidence

    @property
    def observable(self) -> bool:
        return self.gp is not None and self.gp.observable

    def init_points(self, cfg: MeshConfig) -> np.ndarray | None:
        """(N, 3) the points for the initial surface, or None."""
        return self.gp.points if self.observable and cfg.ground_points_use in ("init", "both") else None


def training_sequence(seq: Sequence, data: TrainData) -> Sequence:
    """``seq`` restricted to the frames of the training views (held-out images must not shape the geometry)."""
    return frames_of(seq, {k.frame for k in data.pool.keys})


def find_geometry(seq: Sequence, data: TrainData, cfg: MeshConfig, warn: Warn) -> Geometry:
    """Ground points (per ``cfg.ground_points``) and the camera height used by the initial surface."""
    notes: list[str] = []

    def note(msg: str) -> None:
        notes.append(msg)
        warn(msg)

    gp = data.gp  # triangulated by prepare (before the pool, which takes the images they decoded)
    if gp is not None and not gp.observable and data.use_depth:
        note(f"ground points not observable (the depth layer gives the geometry): {gp.reason}")
    check = None
    if gp is not None and gp.observable and cfg.check_holdout_every >= 2 and len(gp) >= 2 * MIN_POINTS:
        gp, check = gp.split(cfg.check_holdout_every)
    geo = Geometry(gp, cfg.camera_height, "prior", notes=notes, check_gp=check)
    if data.use_depth:
        geo.cam_h, geo.source = searched_height(data.pool, cfg), "depth"
    if geo.observable:
        _height_from_points(geo, seq, data, cfg)
    if geo.source == "prior" and not data.use_depth:
        if cfg.init_height_search:
            geo.cam_h, geo.source = searched_height(data.pool, cfg), "plane search"
        why = gp.reason if gp is not None else "mesh.ground_points is off"
        what = (f"the colour-variance plane search ({geo.cam_h:.2f} m), unchecked" if geo.source == "plane search"
                else f"the prior mesh.camera_height ({geo.cam_h:.2f} m), unchecked")
        note(f"geometry not observable: no depth and no triangulated ground ({why}); the camera height is {what}")
    if geo.found is not None:
        _compare_prior(geo, geo.found, "found from the images", cfg, note)
    elif geo.source == "plane search":
        _compare_prior(geo, geo.cam_h, "of the plane search", cfg, note)
    return geo


def _height_from_points(geo: Geometry, seq: Sequence, data: TrainData, cfg: MeshConfig) -> None:
    """Camera height of the frames' mean centres ``data.traj`` over the road's points under their path
    (:func:`pavemap.geometry.road_height.camera_heights`), combined with the prior ``cfg.camera_height`` by
    inverse variance (the points dominate)."""
    gp = geo.gp
    pts = gp.points[gp.road] if gp.road.sum() >= 30 else gp.points
    est = height_estimate(camera_heights(pts, data.traj, np.array([0.0, 0.0, 1.0])))
    for name, e in estimate_camera_height(training_sequence(seq, data), gp).items():
        geo.per_camera[name] = {"found_m": _r(e.median), "spread_m": _r(e.spread), "frames": e.n_centres,
                                "observable": e.observable}
    if not est.observable:
        gp.reason = f"camera height not observable from the ground points: {est.reason}"
        return
    geo.found, geo.stderr = est.median, max(est.stderr, 0.002)
    if geo.source == "depth":  # measured depth stays the height used; the points only check it
        return
    w_found, w_prior = 1.0 / geo.stderr ** 2, 1.0 / cfg.camera_height_prior_sigma ** 2
    geo.cam_h = (w_found * geo.found + w_prior * cfg.camera_height) / (w_found + w_prior)
    geo.source = "ground points"


def _compare_prior(geo: Geometry, height: float, source: str, cfg: MeshConfig, note: Warn) -> None:
    off = (height - cfg.camera_height) / cfg.camera_height
    if abs(off) > cfg.camera_height_warn_frac:
        note(f"camera height {source} {height:.2f} m is {100 * off:+.0f} % off the prior "
             f"mesh.camera_height {cfg.camera_height:.2f} m: a wrong mount height, or poses with a wrong scale "
             f"(x{height / cfg.camera_height:.2f}); using {geo.cam_h:.2f} m")


def add_point_depth(pool: PixelPool, gp: GroundPoints, scale: float, cameras: dict[str, Camera]) -> PixelPool:
    """The pool with the ground points' observations as sparse depth: the pool pixel under each observation
    (at image ``scale``) gets its camera depth and the observation's exact sub-pixel position (the form of
    :func:`pavemap.mesh.data._depth_samples`). Pixels the pool does not hold (masked) are skipped.
    ``cameras``: the sequence's, for each axis's true factor (:meth:`Camera.scale_xy`: a rounded image size
    makes it differ from ``scale``, and the pool's K uses it)."""
    dev = pool.view.device
    index = {(k.frame, k.camera): i for i, k in enumerate(pool.keys)}
    vmap = np.array([index.get(tuple(k), -1) for k in gp.views], np.int64)
    pv = vmap[gp.obs_view] if len(gp.obs_view) else np.zeros(0, np.int64)
    uv = view_scale_xy(cameras, gp.views, scale)[gp.obs_view] * (gp.obs_uv + 0.5) - 0.5
    ok = pv >= 0
    pv, uv, dep = pv[ok], uv[ok], gp.obs_depth[ok]
    W = int(pool.uv[:, 0].max().item()) + 2 if len(pool) else 1
    H = int(pool.uv[:, 1].max().item()) + 2 if len(pool) else 1
    code = pool.view.cpu() * (W * H) + pool.uv[:, 1].cpu().round().long() * W + pool.uv[:, 0].cpu().round().long()
    order = torch.argsort(code)
    q = torch.from_numpy(pv * (W * H) + np.rint(uv[:, 1]).astype(np.int64) * W + np.rint(uv[:, 0]).astype(np.int64))
    pos = torch.searchsorted(code[order], q).clamp(max=len(code) - 1)
    hit = code[order][pos] == q
    rows = order[pos[hit]].to(dev)
    depth = torch.zeros(len(pool), dtype=torch.float32, device=dev) if pool.depth is None else pool.depth.clone()
    new_uv = pool.uv.clone()
    depth[rows] = torch.from_numpy(dep[hit.numpy()].astype(np.float32)).to(dev)
    new_uv[rows] = torch.from_numpy(uv[hit.numpy()].astype(np.float32)).to(dev)
    return dataclasses.replace(pool, depth=depth, uv=new_uv)


def point_vertices(gp: GroundPoints | None, spec: GridSpec) -> np.ndarray:
    """(ny, nx) bool: the grid vertices nearest to a ground point (what the points observe)."""
    out = np.zeros(spec.shape, bool)
    if gp is None or not len(gp):
        return out
    i = np.rint((gp.points[:, 0] - spec.x0) / spec.res).astype(np.int64)
    j = np.rint((gp.points[:, 1] - spec.y0) / spec.res).astype(np.int64)
    ok = (i >= 0) & (j >= 0) & (i < spec.nx) & (j < spec.ny)
    out[j[ok], i[ok]] = True
    return out


def check_surface(gp: GroundPoints, grid: GridSpec, heights: np.ndarray, offset: float = 0.0,
                  road_only: bool = False, **kw) -> SurfaceCheck:
    """The run's self-check: a height raster (ny, nx) on ``grid`` (raised by ``offset`` metres) against the
    triangulated ground points (those inside the raster). ``flagged`` when the surface is off; see
    :func:`pavemap.geometry.triangulate.check_residuals` for the thresholds (``kw``)."""
    if not gp.observable:
        return SurfaceCheck(0, float("nan"), float("nan"), float("nan"), float("nan"), True,
                            f"surface not checkable: {gp.reason}")
    pts = gp.points[gp.road] if road_only else gp.points
    return check_height_field(pts, grid, np.asarray(heights, np.float64) + offset, **kw)


def height_observed(spec: GridSpec, radius_m: float, *clouds: GroundPoints | np.ndarray | None) -> np.ndarray:
    """(ny, nx) bool: grid vertices within ``radius_m`` of a height measurement: the ground points of each
    GroundPoints and the (N, 3) points of each array (depth pixels cast on their poses) in ``clouds``.

    Why not "a training pixel reaches it": 20-30 m past the last frame a forward camera sees the road at a
    few degrees, its colour but not its height; there the surface is the road's grade continued and the
    cross-section carried along the road, and its height error was 4-17 cm against 2.4 cm within 2 m of a
    ground point (nuScenes-like, no depth). A defect there is mapped, and says its ground was not observed.
    """
    from scipy import ndimage

    seeds = np.zeros(spec.shape, bool)
    for c in clouds:
        pts = c.points if isinstance(c, GroundPoints) else c
        if pts is None or not len(pts):
            continue
        i = np.rint((pts[:, 0] - spec.x0) / spec.res).astype(np.int64)
        j = np.rint((pts[:, 1] - spec.y0) / spec.res).astype(np.int64)
        ok = (i >= 0) & (j >= 0) & (i < spec.nx) & (j < spec.ny)
        seeds[j[ok], i[ok]] = True
    if not seeds.any():
        return seeds
    return ndimage.distance_transform_edt(~seeds) * spec.res <= radius_m


#: The anchoring fit: ten times the initial relief's bending and slope weights, so the correction is the
#: drift, not the detail (which training keeps). Measured: kitti-like seed 23 no depth 2.97 -> 2.86 cm.
ANCHOR_FIT = ReliefFit(curv_s=30.0, curv_t=3.0, slope=3.0)


def anchor_correction(points: np.ndarray | None, spec: GridSpec, heights: np.ndarray, vertex_xy: np.ndarray,
                      traj_xy: np.ndarray) -> np.ndarray | None:
    """(Nv,) float64 correction that puts a trained surface back on the height measurements, or None.

    points (N, 3) the measurements (the fitted ground points, or cast depth pixels where depth is given);
    heights (ny, nx) the surface on ``spec`` (NaN off the crop); vertex_xy (Nv, 2) the kept vertices;
    traj_xy (F, 2) the trajectory. The points' residuals to the surface (point minus surface) are fitted in
    road coordinates by :func:`pavemap.mesh.relief.fit_relief` and sampled at the vertices.

    Why: the photometric loss barely constrains a uniform lift of the whole surface (a view sees the same
    texture a little nearer or farther), and training drifted it by 2-3 cm on the bench drives, while the
    ground points measure height directly and without bias (median residual below 1 mm on the truth). With
    sparse depth the depth loss alone did not hold it either: +2.6 cm on the kitti-like bench drive.
    """
    from pavemap.geometry.triangulate import sample_grid
    from pavemap.mesh.init_surface import road_relief
    if points is None or len(points) == 0 or len(traj_xy) < 2:
        return None
    z = sample_grid(spec, heights, points[:, :2])
    ok = np.isfinite(z)
    if ok.sum() < 100 or np.linalg.norm(np.diff(traj_xy, axis=0), axis=1).sum() < 2.0:
        return None
    return road_relief(traj_xy, points[ok, :2], points[ok, 2] - z[ok], vertex_xy, ANCHOR_FIT)


def self_check(geo: Geometry, spec: GridSpec, heights: np.ndarray, valid: np.ndarray, observed: np.ndarray,
               cfg: MeshConfig, warn: Warn) -> dict:
    """The ``geometry`` entry of stage 1's metrics.json, issuing its warnings through ``warn``.

    heights (ny, nx) the final surface, valid (ny, nx) its crop, observed (ny, nx) the vertices some training
    pixel or ground point reaches. ``trustworthy`` is False when the surface disagrees with the ground points
    (``cfg.check_max_bias_m`` / ``check_max_rms_m`` / ``check_max_p90_m``) or the geometry was not observable; less than
    ``cfg.min_observed_fraction`` of the vertices observed is a warning of its own.
    """
    out: dict = {
        "source": geo.source, "ground_points": 0 if geo.gp is None else len(geo.gp),
        "observable": geo.observable or geo.source == "depth",
        "camera_height": {"used_m": _r(geo.cam_h), "found_m": _r(geo.found), "stderr_m": _r(geo.stderr),
                          "prior_m": cfg.camera_height, "prior_sigma_m": cfg.camera_height_prior_sigma,
                          "per_camera": geo.per_camera},
    }
    frac = float(observed[valid].mean()) if valid.any() else 0.0
    out["observed_fraction"] = round(frac, 4)
    issues = [n for n in geo.notes if n.startswith("geometry not observable")]
    if geo.gp is not None and geo.gp.observable:
        h = np.where(valid, heights, np.nan).astype(np.float64)
        held = geo.check_gp is not None and geo.check_gp.observable
        c = check_surface(geo.check_gp if held else geo.gp, spec, h, max_bias_m=cfg.check_max_bias_m,
                          max_rms_m=cfg.check_max_rms_m, max_p90_m=cfg.check_max_p90_m)
        out["check"] = {"points": c.n, "held_out": held, "median_m": _r(c.median), "robust_rms_m": _r(c.robust_rms),
                        "p90_abs_m": _r(c.p90), "frac_within_5cm": _r(c.frac_within), "flagged": c.flagged,
                        "reason": c.reason, "max_bias_m": cfg.check_max_bias_m, "max_rms_m": cfg.check_max_rms_m,
                        "max_p90_m": cfg.check_max_p90_m}
        if c.flagged:
            issues.append(f"surface not trustworthy: {c.reason}")
            warn(issues[-1])
    out["trustworthy"] = not issues
    if frac < cfg.min_observed_fraction:
        # Not a wrong surface: ground no camera saw (behind the first frame, past the last) holds no defect
        # either, but its heights are a guess, and a short drive is mostly that.
        issues.append(f"mesh mostly unobserved: only {100 * frac:.0f} % of its vertices have a measured height (a "
                      f"ground point or depth sample within mesh.observed_radius_m {cfg.observed_radius_m:g} m; "
                      f"mesh.min_observed_fraction {cfg.min_observed_fraction:.2f}); heights elsewhere are the road "
                      "carried along from where it was measured (bev_observed.npy)")
        warn(issues[-1])
    out["warnings"] = issues + [n for n in geo.notes if n not in issues]
    return out


def _r(v: float | None, nd: int = 4) -> float | None:
    return None if v is None or not np.isfinite(v) else round(float(v), nd)


def mark_observed(instances: list, mesh) -> None:  # noqa: ANN001 - DefectInstance list, RoadMesh
    """Set ``extra["observed"]`` of each defect instance: whether the mesh vertex nearest its centre is
    observed (a training pixel or ground point reaches it); and ``extra["texture_contested"]``: whether it lies
    where the texture may hold a vehicle (:mod:`pavemap.mesh.texture_check`: a detection there may have fired
    on one). Each is left unset when the mesh has no such layer."""
    s = mesh.surface
    for key, layer in (("observed", mesh.observed), ("texture_contested", mesh.contested)):
        if layer is None:
            continue
        on = layer.cpu().numpy()
        for inst in instances:
            i = int(round((float(inst.centroid[0]) - s.x0) / s.res))
            j = int(round((float(inst.centroid[1]) - s.y0) / s.res))
            inside = 0 <= j < on.shape[0] and 0 <= i < on.shape[1]
            inst.extra[key] = bool(inside and on[j, i])


def depth_image(gp: GroundPoints, view_id: int, width: int, height: int, scale: float = 1.0) -> np.ndarray:
    """(height, width) float32 sparse depth (m, 0 = none) of one view at ``scale``: the ground points'
    camera depths at their pixels, the form of a sequence's depth layer and of ``PixelPool.depth``."""
    sel = gp.obs_view == view_id
    ui = np.rint(scale * (gp.obs_uv[sel] + 0.5) - 0.5).astype(np.int64)
    ok = (ui[:, 0] >= 0) & (ui[:, 1] >= 0) & (ui[:, 0] < width) & (ui[:, 1] < height)
    out = np.zeros((height, width), np.float32)
    out[ui[ok, 1], ui[ok, 0]] = gp.obs_depth[sel][ok]
    return out
