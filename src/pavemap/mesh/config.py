"""Stage-1 configuration (SPEC §1) with the nuScenes-like and KITTI-like presets.

Measured effects of the settings (best values, before / after) are in docs/history's stage-1 section
and ``bench/results/mesh.json`` / ``pose.json``; the comments here say why a setting exists.
"""

from __future__ import annotations

import math
import typing
from dataclasses import asdict, dataclass, fields
from typing import Literal

from pavemap.device import CHOICES as DEVICE_CHOICES
from pavemap.device import is_device_name
from pavemap.errors import PavemapError

PRESETS = ("nuscenes", "kitti")
PosePer = Literal["frame", "view"]
GroundMode = Literal["auto", "always", "off"]
GroundUse = Literal["init", "depth", "both"]
ReliefMethod = Literal["road", "bins"]


@dataclass
class MeshConfig:
    """Everything stage 1 needs; the defaults are the SPEC's (paper / RoMe) values.

    Speed knobs (ours, not the paper's): training renders at ``render_scale`` of the image size and
    samples ``pixels_per_step`` pixels per optimizer step from all training views, of which the first
    ``height_pixels_per_step`` also train the height MLP (the MLP runs only on their triangles'
    vertices, the others use the heights cached at the last refresh); one epoch visits
    ``pixel_fraction`` of all usable pixels at that scale once.
    """

    resolution: float = 0.1  # m per cell
    crop_m: float = 7.0  # keep vertices within this distance of the camera trajectory
    # ... and of the road the first and last frames' cameras look at, this far along their view direction
    # (a forward camera's detections 20-40 m past the last frame need a surface there; 0: trajectory only)
    view_range_m: float = 30.0
    pe_levels: int = 5  # L of the positional encoding (5 nuScenes, 4 KITTI)
    hidden: int = 128
    # Adam epochs after the closed-form fits (SPEC: 7). 0 by default: the surface comes from the ground points or
    # depth (relief and anchor fits) and the colours, semantics and exposures from the bakes, and on the bench
    # drives and real KITTI the epochs changed neither measurably at 2-4x the time (docs/history, "The closed-form
    # stage 1"). 7 runs the SPEC's training on top; pose refinement's joint Adam steps need epochs too.
    epochs: int = 0
    lr_rgb: float = 0.1
    lr_sem: float = 0.1
    lr_height: float = 0.001
    lr_pose: float = 0.001  # SPEC's camera-pose rate, used for the translation correction (m)
    # The rotation correction (rad) gets its own rate: Adam moves a parameter ~lr per step, and a rotation
    # of lr rad shifts ground seen at 5-20 m by 5-20 lr metres, so at the SPEC's rate the rotation would
    # jump 10x further than the translation and oscillate.
    lr_pose_rot: float = 0.0001
    pose_warmup: float = 0.25  # fraction of the steps before pose refinement starts
    # Before training, per-view Gauss-Newton alignment to the baked texture and depth (pavemap.mesh.pose):
    # rounds x iterations, on at most this many pixels per view. 0 iterations: Adam's joint refinement only.
    pose_align_iters: int = 8
    pose_align_rounds: int = 2
    pose_align_pixels_per_view: int = 1000
    # How far off the raw poses may be (1 sigma, degrees and metres): the alignment's prior (align_poses).
    pose_prior_deg: float = 0.3
    pose_prior_m: float = 0.2
    pose_bake_every: int = 10  # with pose refinement: steps between re-bakes of the colours on the current poses
    lr_decay_final: float = 0.1  # learning rates decay exponentially to this fraction by the last step
    lr_height_decay_final: float = 0.1  # the height MLP's own decay target (1.0: constant SPEC rate)
    w_rgb: float = 1.0
    w_sem: float = 0.5
    w_depth: float = 1.0  # lambda_depth, used only where depth maps exist
    # Depth residuals whose height equivalent |D_render - D_gt| * |d_z| exceeds this are ignored (a facade,
    # a pole: not road). In height units, not depth: at 20 m a 0.1 m height error is a >1 m depth residual.
    depth_outlier_m: float = 0.25
    w_smooth: float = 1.0
    render_scale: float = 0.25  # training image scale
    eval_scale: float = 0.25  # held-out evaluation image scale
    pixels_per_step: int = 65536  # pixels rendered per step (colour / semantic / depth losses)
    height_pixels_per_step: int = 8192  # of which these also train the height MLP (its cost per step)
    depth_first: bool = True  # pixels with measured depth go first, i.e. into the height-training rays
    pixel_fraction: float = 1.0
    frame_stride: int = 1
    holdout_every: int = 10  # every k-th frame is held out for metrics (0: none)
    seed: int = 0
    device: str = "auto"  # auto, cpu, cuda, cuda:N (pavemap.device.resolve_device)
    threads: int | None = None  # torch CPU threads during the run (None or 0: leave torch's setting)
    # numpy's and scipy's BLAS threads during stage 1 (0: the libraries' own, one per core). Stage 1 makes
    # thousands of tiny LAPACK calls (3 x 3 inverses and solves) that a BLAS thread pool hands off and waits for.
    # On the 2-core bench machine one thread ran the whole `pavemap run` as fast when idle (wall ratio 1.05 demo,
    # 1.00 nuScenes-like 40 x 6) with 18-19 % less CPU, and 20 % / 15 % faster with another process on a core
    # (bench/results/cuda.json, blas_threads; same defects)
    blas_threads: int = 1
    pose_refine: bool = False
    # "frame": the cameras of a frame move together (one rigid rig: the error of an ego pose; SPEC: "a small
    # SE(3) correction per frame"); "view": every image its own correction (per-camera calibration errors).
    pose_per: PosePer = "frame"
    # The camera mount height above the road (m): a prior with 1-sigma ``camera_height_prior_sigma``, not a
    # constant. Measured depth or the triangulated ground points override it; a found height more than
    # ``camera_height_warn_frac`` off it is a warning (a wrong mount height, or poses with a wrong scale).
    camera_height: float = 1.5
    camera_height_prior_sigma: float = 0.15
    camera_height_warn_frac: float = 0.10
    # Road geometry from the images (pavemap.mesh.ground_points): "auto" triangulates ground points when no
    # training view has a depth layer, "always" also with depth (the self-check then has evidence), "off" never.
    ground_points: GroundMode = "auto"
    # Where the points go: the initial surface only ("init"), or sparse depth pixels of the training pool
    # ("depth": the initial surface from them and the depth loss, which keeps the MLP on the points; height
    # RMSE 2.9 vs 3.6 cm kitti-like, 5.6 vs 6.6 cm nuscenes-like), or both.
    ground_points_use: GroundUse = "depth"
    ground_points_scale: float = 1.0  # image scale for matching (0.5: ~3x faster, fewer points)
    ground_points_corners: int = 400  # corners per reference view (more: denser points, longer matching)
    # The run's self-check against the ground points: a median residual or a robust RMS beyond these (m)
    # makes the surface "not trustworthy"; a smaller observed fraction of the mesh's vertices is a warning.
    # After training, fit the residuals of the height measurements (ground points, or the depth pixels where
    # depth is given) to the surface in road coordinates and add them (pavemap.mesh.geometry.anchor_correction):
    # training drifts a surface by a few cm where the photometric loss cannot tell heights apart.
    anchor_to_points: bool = True
    # Every n-th ground point is held out of the surface (initial relief, depth loss, anchoring) and checks it
    # (0: check against the points the surface was fitted to, which cannot see a bias).
    check_holdout_every: int = 8
    check_max_bias_m: float = 0.05
    check_max_rms_m: float = 0.10
    # A tenth of the held-out points farther off than this flags the surface: a segment whose surface was tilted
    # by metres at one end had median 8 mm and robust RMS 3 cm, but p90 2.6 m (KITTI-00 drive, issue 17).
    check_max_p90_m: float = 0.25
    min_observed_fraction: float = 0.5
    # A vertex's height counts as observed within this distance of a ground point or depth sample (the
    # ``observed`` layer; pavemap.mesh.geometry.height_observed); a training pixel alone sees colour, not height.
    observed_radius_m: float = 2.0
    # Start from the binned measured ground where depth exists (pavemap.mesh.init_surface.depth_relief).
    init_from_depth: bool = True
    # How the measured points become the initial relief: "road", a regularised least-squares fit in road
    # coordinates (pavemap.mesh.relief; initial-surface RMSE over observed vertices without depth 5.6 -> 2.5 cm
    # nuScenes-like, 5.6 -> 1.7 cm kitti-like), or "bins", the per-bin medians with fills below.
    init_relief: ReliefMethod = "road"
    # After the initial bake gives the vertices their classes, fit the road relief again with the surface free
    # to step between road-class vertices and the others (a kerb; pavemap.mesh.relief.fit_relief's side_q):
    # the smooth fit rounded a 12 cm kerb off over a metre on either side (docs/history, geometry without LiDAR).
    kerb_steps: bool = True
    # The share of a vertex's semantic votes for other classes that puts it off the road for the kerb refit
    # (nuScenes-like height RMSE over observed vertices 2.14 / 1.93 / 2.11 cm at 0.5 / 0.7 / 0.85).
    kerb_off_share: float = 0.7
    init_cell_m: float = 1.0  # bin size of that initial surface (m)
    # Finer bins (m) holding the median of what the coarse bins miss, where >= 3 points fall: keeps curbs
    # sharp (0 turns it off).
    init_fine_cell_m: float = 0.3
    # Ground no depth point reaches takes the relief measured at the same cross-track offset within about this
    # many metres along the road (0: isotropic fill only; see init_surface.fill_along_track).
    init_along_fill_m: float = 4.0
    init_height_search: bool = True  # refine the initial plane height by multi-view colour agreement
    max_dist: float = 80.0  # longest ray considered (m)
    # Closed-form colours on the current surface (pavemap.mesh.bake) before the first step and after the last:
    # in a CPU budget Adam alone leaves the colours noisier than the surface supports.
    bake_init: bool = True
    # Pixels whose colour differs from the road the other views see by more than this (RGB distance, 0-1 scale)
    # after the initial bake are left out of training (pavemap.mesh.bake.static_pixels): a vehicle passing the
    # camera paints itself onto the road in a few views only. 0: keep every pixel.
    moving_cutoff: float = 0.0
    # and only where they form a blob this many pixels (at render_scale) from its centre to its edge: paint edges
    # and texture a centimetre off are thin lines, a vehicle is a blob (bench/moving_bench.py). 0: every pixel.
    moving_blob_px: int = 2
    # After the final bake, mark the vertices whose texture some views disagree with (pavemap.mesh.texture_check):
    # where a vehicle covered the road in most views it *is* the texture, and the report says where that may be.
    # A pixel disagrees beyond ``texture_cutoff`` (RGB distance) in a blob ``texture_blob_px`` from its centre to
    # its edge; a square of ``texture_block_m`` is contested where that is at least ``texture_min_share`` of its
    # pixels from at least ``texture_min_views`` views, and reported in patches of ``texture_min_patch_m2``
    # (bench/moving_bench.py: a painted overtaking vehicle against the clean drive).
    texture_check: bool = True
    texture_cutoff: float = 0.15
    texture_blob_px: int = 1
    texture_min_share: float = 0.1
    texture_min_views: int = 2
    texture_block_m: float = 0.5  # a vertex sees a handful of pixels at render scale; a vehicle, square metres
    texture_min_patch_m2: float = 1.0
    bake_final: bool = True
    # Jacobi steps from the weighted mean towards the least-squares colours in the final bake (bake_colours):
    # the mean blurs, the exact solution overfits single pixels.
    bake_sharpen_iters: int = 2
    # Rounds of fitting each view's exposure (a gain and an offset, pavemap.mesh.exposure) in the final bake:
    # real cameras change exposure along a drive; held-out views take their neighbours' (0: off).
    exposure_rounds: int = 2
    bake_fill_sigma: float = 1.0  # cells: vertices no training pixel hits take their neighbours' colour
    # Only pixels of ground classes (SemanticClass.ground: road, markings, kerb, sidewalk, terrain) and unlabelled
    # ones colour the texture: a wall, a trailer or a bus the segmenter calls "building", cast along its rays,
    # would paint its side onto the road behind it. The semantic bake keeps every labelled pixel.
    bake_ground_only: bool = True
    height_refresh_steps: int = 16  # steps between full-grid height re-evaluations used by the march
    resume: bool = True  # continue from DIR/checkpoint.pt when it matches
    # Long drives (pavemap.mesh.segments): a path longer than 1.5 x ``segment_m`` is cut into segments of about
    # this length (m of path) overlapping by ``segment_overlap_m``, each reconstructed from its own views only
    # and blended into one surface; memory then depends on the segment, not the drive (0: one piece). Longer
    # segments re-process fewer overlap views per metre; a segment's memory grows with its views.
    segment_m: float = 250.0
    segment_overlap_m: float = 20.0
    # Frames of another pass (a loop, a U-turn) within this distance of a segment's path join its views, so that
    # revisited road is one surface seen by both passes; a later pass that stays on an earlier pass's road for
    # 2 x ``segment_overlap_m`` or more is reconstructed there by the earlier pass's segments only.
    segment_revisit_m: float = 10.0
    # ... one of them every this many metres along its pass (0: all): the own pass already sees the road every
    # metre, and every revisit view costs stage 1 as much as an own one (see the long-drive bench, docs/history).
    segment_revisit_spacing_m: float = 1.5
    # A standing vehicle: frames within this distance (m) of the last frame kept add nothing but memory.
    segment_min_step_m: float = 0.1
    # After the closed form (and the initial bake), move the surface by the global offset at which the training
    # views agree best on colour (pavemap.mesh.refine_run; docs/refine.md): a surface +-10 cm off ends within
    # 0.3 cm (kitti-like) / 0.4 cm (nuScenes-like). Off: on top of the ground points it changed the height RMSE by
    # -3 % / +4 % and the bias from 0.49 to 0.23 cm / -0.17 to -0.63 cm, at +6 / +7 s (bench/results/refine.json).
    refine: bool = False
    # Report in metrics.json ("consistency") the global offset the views' consistency asks of the final surface,
    # and warn beyond ``check_max_consistency_m``. Off by default: +2.4 / +2.8 s on the bench drives; it reads
    # -0.3 / -0.1 cm on their closed forms (docs/refine.md).
    consistency_check: bool = False
    check_max_consistency_m: float = 0.03
    max_bad_steps: int = 20  # consecutive non-finite steps before giving up

    def __post_init__(self) -> None:
        self.validate()

    @classmethod
    def preset(cls, name: str) -> MeshConfig:
        """``nuscenes``: crop 7 m, L=5; ``kitti``: crop 5 m, L=4 (RoMe's settings)."""
        if name == "nuscenes":
            return cls(crop_m=7.0, pe_levels=5)
        if name == "kitti":
            return cls(crop_m=5.0, pe_levels=4, camera_height=1.65)  # KITTI states its mount height
        raise PavemapError(f"unknown mesh preset {name!r}; choose one of {', '.join(PRESETS)}")

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> MeshConfig:
        names = {f.name for f in fields(cls)}
        return cls(**{k: v for k, v in d.items() if k in names})

    def validate(self) -> None:
        """Raise PavemapError naming ``mesh.<field>`` on a value of the wrong type or one that cannot work."""
        _check_types(self)
        for name in ("resolution", "crop_m", "render_scale", "eval_scale", "max_dist", "pixel_fraction",
                     "bake_fill_sigma", "pose_prior_deg", "pose_prior_m", "camera_height", "init_cell_m",
                     "depth_outlier_m", "lr_decay_final", "lr_height_decay_final", "camera_height_prior_sigma",
                     "camera_height_warn_frac", "ground_points_scale", "check_max_bias_m", "check_max_rms_m",
                     "check_max_p90_m", "observed_radius_m", "check_max_consistency_m"):
            _require(self, name, lambda v: v > 0, "must be positive")
        for name in ("epochs", "holdout_every", "pe_levels", "bake_sharpen_iters", "pose_align_iters",
                     "pose_align_rounds", "exposure_rounds", "seed", "init_fine_cell_m", "check_holdout_every",
                     "view_range_m", "segment_m", "segment_overlap_m", "segment_revisit_m", "segment_revisit_spacing_m",
                     "segment_min_step_m",
                     "moving_cutoff", "moving_blob_px", "texture_cutoff", "texture_min_share", "texture_min_views",
                     "texture_min_patch_m2", "texture_block_m",
                     "texture_blob_px",
                     "init_along_fill_m", "lr_rgb", "lr_sem", "lr_height",
                     "lr_pose", "lr_pose_rot",
                     "w_rgb", "w_sem", "w_depth", "w_smooth"):
            _require(self, name, lambda v: v >= 0, "must be >= 0")
        for name in ("frame_stride", "pixels_per_step", "height_pixels_per_step", "hidden", "pose_bake_every",
                     "pose_align_pixels_per_view", "height_refresh_steps", "max_bad_steps", "ground_points_corners"):
            _require(self, name, lambda v: v >= 1, "must be >= 1")
        _require(self, "pose_warmup", lambda v: 0.0 <= v <= 1.0, "must be in [0, 1]")
        _require(self, "threads", lambda v: v is None or v >= 0, "must be >= 0 (0 or null: torch's setting)")
        _require(self, "blas_threads", lambda v: v >= 0, "must be >= 0 (0: the BLAS libraries' own)")
        _require(self, "pose_per", lambda v: v in typing.get_args(PosePer),
                 f"must be one of {', '.join(typing.get_args(PosePer))}")
        _require(self, "device", is_device_name, f"must be {DEVICE_CHOICES}")
        for name, kind in (("ground_points", GroundMode), ("ground_points_use", GroundUse)):
            choices = typing.get_args(kind)
            _require(self, name, lambda v, c=choices: v in c, f"must be one of {', '.join(choices)}")
        _require(self, "min_observed_fraction", lambda v: 0.0 <= v <= 1.0, "must be in [0, 1]")
        _require(self, "kerb_off_share", lambda v: 0.0 < v <= 1.0, "must be in (0, 1]")
        _require(self, "ground_points_scale", lambda v: v <= 2.0, "must be in (0, 2]")


def _require(cfg: MeshConfig, name: str, ok: typing.Callable[[object], bool], what: str) -> None:
    value = getattr(cfg, name)
    if isinstance(value, float) and not math.isfinite(value) or not ok(value):
        raise PavemapError(f"mesh.{name} {what}, got {value!r}")


def _check_types(cfg: MeshConfig) -> None:
    """Each field's value against its annotation (bool, int, float, str, int | None, a Literal)."""
    hints = typing.get_type_hints(MeshConfig)
    for f in fields(cfg):
        value, hint = getattr(cfg, f.name), hints[f.name]
        allowed = typing.get_args(hint) if typing.get_origin(hint) is not Literal else (str,)
        kinds = allowed or (hint,)
        if value is None and type(None) in kinds:
            continue
        if bool in kinds:
            good = isinstance(value, bool)
        elif float in kinds:
            good = isinstance(value, int | float) and not isinstance(value, bool)
        elif int in kinds:
            good = isinstance(value, int) and not isinstance(value, bool)
        else:
            good = isinstance(value, str)
        if not good:
            names = " or ".join("null" if k is type(None) else k.__name__ for k in kinds)
            raise PavemapError(f"mesh.{f.name} must be {names}, got {value!r}")


@dataclass
class GroundConfig:
    """Knobs of :func:`pavemap.mesh.ground_points.find_ground_points` (defaults chosen on the synthetic and KITTI
    benches)."""

    scale: float = 1.0  # image scale for matching
    prior_height: float = 1.5  # m: centres the depth search and the range mask, never enters the geometry
    min_range: float = 2.0  # m, ground distance of usable pixels on the prior plane
    max_range: float = 25.0
    horizon_margin_deg: float = 3.0  # pixels must look at least this far below the horizon
    max_gap: int = 3  # frames between a reference view and its partners
    max_partners: int = 4
    min_overlap: float = 0.15  # fraction of the reference's ground that a partner must see
    max_corners: int = 400
    min_distance: int = 7  # px between corners
    quality: float = 0.003  # goodFeaturesToTrack quality level (road texture is weak)
    patch: int = 11  # sweep patch side (px)
    sweep_range: float = 0.5  # +- log depth around the prior plane's depth (prior height x0.6 .. x1.65)
    coarse_px: float = 2.0  # coarse hypothesis spacing along the epipolar line (px)
    sweep_max_steps: int = 200  # at most this many coarse hypotheses (the spacing grows beyond)
    sparse_coarse: bool = True  # coarse sweep on every other pixel of the patch (3x faster, same points)
    min_ncc: float = 0.8
    min_drop: float = 0.05  # NCC must fall by this much 2 px either side of the peak (edges along the line)
    min_contrast: float = 2.0  # grey levels (std of the reference patch)
    max_err_px: float = 1.0  # reprojection error allowed per observation
    min_angle_deg: float = 1.0
    min_views: int = 2
    neighbour_m: float = 0.15  # drop points this far off the robust surface of their neighbours
    # a point matched into one partner only is checked at the depth found in the other views of its camera
    # within max_gap frames: where every one that sees the spot on its ground scores below this NCC, it is
    # dropped (a moving vehicle's flank matches one neighbouring frame, not the next; the road still scores)
    static_ncc: float = 0.5
    # the far pass: every ``far_every``-th view matches corners between 0.8 x max_range and far_range into the
    # first later view of its camera ``far_baseline_m`` away, so the road ahead of a drive's end is observed
    far_range: float = 60.0  # m (0: no far pass)
    far_baseline_m: float = 4.0
    far_every: int = 2
    far_corners: int = 150
    far_max_gap: int = 15  # frames
    far_horizon_deg: float = 1.5  # the far pass's horizon margin (3 degrees end the road 31 m ahead of 1.65 m)
    corridor_m: float = 8.0  # without semantics: ground must lie this close to the trajectory
    use_semantics: bool = True
