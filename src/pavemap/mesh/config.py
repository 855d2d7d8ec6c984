"""Stage-1 configuration (SPEC §1) with the nuScenes-like and KITTI-like presets."""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields

from pavemap.errors import PavemapError

PRESETS = ("nuscenes", "kitti")


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
    pe_levels: int = 5  # L of the positional encoding (5 nuScenes, 4 KITTI)
    hidden: int = 128
    epochs: int = 7
    lr_rgb: float = 0.1
    lr_sem: float = 0.1
    lr_height: float = 0.001
    lr_pose: float = 0.001  # SPEC's camera-pose rate, used for the translation correction (m)
    # The rotation correction (rad) gets its own rate: Adam moves a parameter ~lr per step, and a rotation
    # of lr rad shifts ground seen at 5-20 m by 5-20 lr metres, i.e. at the SPEC's rate the rotation would
    # jump 10x further than the translation and oscillate (0.3 deg grew to 2.5 deg on the test scene).
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
    device: str = "auto"
    threads: int | None = None  # torch CPU threads during the run (None: leave torch's setting)
    pose_refine: bool = False
    # "frame": the cameras of a frame move together (one rigid rig: the error of an ego pose; SPEC: "a small
    # SE(3) correction per frame"); "view": every image its own correction (per-camera calibration errors).
    # On the nuScenes-like drive per frame reached 0.10 m / 0.14 deg, per camera 0.13 m / 0.28 deg (pose.json).
    pose_per: str = "frame"
    camera_height: float = 1.5  # initial road plane below the median camera centre (m)
    init_from_depth: bool = True  # start from the binned measured ground where depth exists (see _depth_relief)
    init_cell_m: float = 1.0  # bin size of that initial surface (m): 1 m measured best of 0.25-2 m
    # Finer bins (m) holding the median of what the 1 m bins miss, where >= 3 points fall: keeps curbs sharp
    # (0.3 m measured best of 0.1-0.5 m on the nuScenes-like drive; 0 turns it off).
    init_fine_cell_m: float = 0.3
    # Ground no depth point reaches takes the relief measured at the same cross-track offset within about this
    # many metres along the road (0: isotropic fill only; see train._fill_along_track). Initial surface RMSE
    # nuScenes-like / kitti-like: 0.022 / 0.035 m without; 0.015 / 0.022 (2 m), 0.014 / 0.013 (4 m), 0.014 / 0.012 (8).
    init_along_fill_m: float = 4.0
    init_height_search: bool = True  # refine the initial plane height by multi-view colour agreement
    max_dist: float = 80.0  # longest ray considered (m)
    # Closed-form colours on the current surface (pavemap.mesh.bake) before the first step and after the last:
    # Adam alone left the held-out PSNR ~1.6 dB below what the surface supports in a CPU budget.
    bake_init: bool = True
    bake_final: bool = True
    # Jacobi steps from the weighted mean towards the least-squares colours in the final bake (bake_colours):
    # 2 measured best of 0-3 (the mean blurs, the exact solution overfits).
    bake_sharpen_iters: int = 2
    bake_fill_sigma: float = 1.0  # cells: vertices no training pixel hits take their neighbours' colour
    height_refresh_steps: int = 16  # steps between full-grid height re-evaluations used by the march
    resume: bool = True  # continue from DIR/checkpoint.pt when it matches
    max_bad_steps: int = 20  # consecutive non-finite steps before giving up

    @classmethod
    def preset(cls, name: str) -> MeshConfig:
        """``nuscenes``: crop 7 m, L=5; ``kitti``: crop 5 m, L=4 (RoMe's settings)."""
        if name == "nuscenes":
            return cls(crop_m=7.0, pe_levels=5)
        if name == "kitti":
            return cls(crop_m=5.0, pe_levels=4)
        raise PavemapError(f"unknown mesh preset {name!r}; choose one of {', '.join(PRESETS)}")

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> MeshConfig:
        names = {f.name for f in fields(cls)}
        return cls(**{k: v for k, v in d.items() if k in names})

    def validate(self) -> None:
        """Raise PavemapError on values that cannot work."""
        positive = ("resolution", "crop_m", "render_scale", "eval_scale", "max_dist", "pixel_fraction",
                    "bake_fill_sigma", "pose_prior_deg", "pose_prior_m")
        for name in positive:
            if not getattr(self, name) > 0:
                raise PavemapError(f"mesh config: {name} must be positive, got {getattr(self, name)}")
        for name in ("epochs", "holdout_every", "pe_levels", "bake_sharpen_iters", "pose_align_iters",
                     "pose_align_rounds"):
            if getattr(self, name) < 0:
                raise PavemapError(f"mesh config: {name} must be >= 0, got {getattr(self, name)}")
        if min(self.frame_stride, self.pixels_per_step, self.height_pixels_per_step, self.hidden,
               self.pose_bake_every) < 1:
            raise PavemapError("mesh config: frame_stride, pixels_per_step, height_pixels_per_step, hidden and "
                               "pose_bake_every must be >= 1")
        if not 0.0 <= self.pose_warmup <= 1.0:
            raise PavemapError(f"mesh config: pose_warmup must be in [0, 1], got {self.pose_warmup}")
        if self.pose_per not in ("view", "frame"):
            raise PavemapError(f"mesh config: pose_per must be view or frame, got {self.pose_per!r}")
        if self.device not in ("auto", "cpu", "cuda") and not self.device.startswith("cuda:"):
            raise PavemapError(f"mesh config: device must be auto, cpu or cuda, got {self.device!r}")
