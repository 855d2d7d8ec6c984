"""Camera poses from plain video: incremental SfM with pycolmap, metric scale from the mount height.

Steps (:func:`sfm_poses`):

1. SIFT features, sequential matching (video order, with loop-free overlap), incremental
   mapping with the known intrinsics held fixed (PINHOLE, one camera). The largest model
   is kept; images it could not register are reported and left out.
2. Road points: SfM points that project into the lower-middle of their nearest
   camera's image (where the road is for a forward-looking car camera) and lie below it.
   "Up" is the cameras' mean −y axis with its component along the drive removed.
3. Scale: each road point under the driven path is paired with the camera that later
   passes over it (nearest in the ground plane), which makes the height independent of
   the road's slope; the median of those heights, in SfM units, equals the known
   mounting height ``camera_height`` (metres) → one scale factor. (A global road plane
   was tried first: on a gently rolling road it biased the scale by up to 20 %.)
4. Axes: world z = up, x = the driving direction, origin = the first camera's foot
   point on the road (road at z ≈ 0).
"""

from __future__ import annotations

import logging
import os
import shutil
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pavemap.errors import PavemapError
from pavemap.types import Camera

log = logging.getLogger(__name__)


@dataclass
class SfmResult:
    T_world_cam: np.ndarray  # (N, 4, 4) float64, metric z-up; rows of unregistered images are NaN
    registered: np.ndarray  # (N,) bool
    scale: float  # metres per SfM unit
    plane_inliers: int
    points: np.ndarray  # (P, 3) float64 SfM points in the metric world
    info: dict = field(default_factory=dict)


def _heights_below_path(X: np.ndarray, C: np.ndarray, up: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Height of each camera path point above road points ``X`` (M, 3) it drives over.

    For each point the camera centre nearest *in the ground plane* is found among all
    frames (a later frame passes over what an earlier one saw ahead), so slopes along
    the road do not bias the height. Returns heights (M,) in SfM units and the mask of
    points within 1.5 typical heights, sideways, of the path (the road the car drove on).
    """
    from scipy.spatial import cKDTree

    def flat(a: np.ndarray) -> np.ndarray:
        return a - np.outer(a @ up, up)

    dist, k = cKDTree(flat(C)).query(flat(X))
    h = (C[k] - X) @ up
    first = np.median(h[h > 0]) if (h > 0).any() else 0.0
    return h, (h > 0) & (dist < 1.5 * first)


def _road_candidates(P: np.ndarray, C: np.ndarray, R_wc: np.ndarray, K: np.ndarray, width: int, height: int,
                     up: np.ndarray) -> np.ndarray:
    """Mask of points ``P`` (M, 3) that look like road: below some camera and inside the lower-middle
    of its image (a forward car camera sees the road there). Points x cameras in blocks of 64 cameras."""
    hit = np.zeros(len(P), dtype=bool)
    for s0 in range(0, len(C), 64):
        Cb, Rb = C[s0 : s0 + 64], R_wc[s0 : s0 + 64]
        rel = P[None] - Cb[:, None]  # (B, M, 3)
        Xc = np.einsum("bji,bmj->bmi", Rb, rel)  # world -> camera: R^T (P - C)
        z = Xc[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = K[0, 0] * Xc[..., 0] / z + K[0, 2]
            v = K[1, 1] * Xc[..., 1] / z + K[1, 2]
        ok = (z > 0) & ((rel @ up) < 0) & (v > K[1, 2] + 0.15 * height) & (v < height)
        ok &= np.abs(u - K[0, 2]) < 0.3 * width
        hit |= ok.any(0)
    return hit


def sfm_poses(images: list[Path], camera: Camera, camera_height: float = 1.5, workdir: str | os.PathLike | None = None,
              overlap: int = 10, num_threads: int = 2, max_features: int = 8192, min_registered: float = 0.6,
              seed: int = 0, peak_threshold: float = 0.003, verbose: bool = False) -> SfmResult:
    """Metric z-up camera-to-world poses (N, 4, 4) for ``images`` (video order) of one ``camera``."""
    try:
        import pycolmap
    except ImportError as e:
        raise PavemapError(f"--poses sfm needs pycolmap: pip install 'pavemap[sfm]' ({e})") from None
    if len(images) < 3:
        raise PavemapError(f"SfM needs at least 3 images, got {len(images)}")
    if camera_height <= 0:
        raise PavemapError(f"camera height must be positive metres, got {camera_height}")
    images = [Path(p) for p in images]
    # COLMAP logs every step at INFO to stderr; keep warnings, report progress ourselves
    old_level = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = int(pycolmap.logging.WARNING) if verbose is False else 0
    folders = {p.parent.resolve() for p in images}
    own_tmp = workdir is None
    work = Path(tempfile.mkdtemp(prefix="pavemap-sfm-")) if own_tmp else Path(workdir)
    work.mkdir(parents=True, exist_ok=True)
    try:
        if len(folders) == 1:
            image_dir = folders.pop()
            names = [p.name for p in images]
        else:  # pycolmap reads from one folder: link the images into one
            image_dir = work / "images"
            image_dir.mkdir(exist_ok=True)
            names = []
            for i, p in enumerate(images):
                name = f"{i:06d}{p.suffix.lower()}"
                if not (image_dir / name).exists():
                    os.symlink(p.resolve(), image_dir / name)
                names.append(name)
        db = work / "database.db"
        if db.exists():
            db.unlink()
        K = camera.K
        reader = pycolmap.ImageReaderOptions()
        reader.camera_model = "PINHOLE"
        reader.camera_params = f"{K[0, 0]},{K[1, 1]},{K[0, 2] + 0.5},{K[1, 2] + 0.5}"  # COLMAP: pixel corner origin
        extraction = pycolmap.FeatureExtractionOptions()
        extraction.num_threads = num_threads
        extraction.sift.max_num_features = max_features
        # road surfaces are low-contrast: a lower peak threshold keeps their (few) features
        extraction.sift.peak_threshold = peak_threshold
        extraction.use_gpu = False
        from tqdm import tqdm

        stages = tqdm(total=4, desc="sfm", unit="stage", disable=None)
        stages.set_postfix_str("features")
        pycolmap.extract_features(db, image_dir, image_names=names, camera_mode=pycolmap.CameraMode.SINGLE,
                                  reader_options=reader, extraction_options=extraction, device=pycolmap.Device.cpu)
        stages.update(1)
        stages.set_postfix_str("matching")
        pairing = pycolmap.SequentialPairingOptions()
        pairing.overlap = overlap
        pairing.quadratic_overlap = True
        matching = pycolmap.FeatureMatchingOptions()
        matching.num_threads = num_threads
        matching.use_gpu = False
        pycolmap.match_sequential(db, matching_options=matching, pairing_options=pairing, device=pycolmap.Device.cpu)
        stages.update(1)
        stages.set_postfix_str("mapping")
        opts = pycolmap.IncrementalPipelineOptions()
        opts.num_threads = num_threads
        opts.ba_refine_focal_length = False  # intrinsics are known; keeps the metric K
        opts.ba_refine_principal_point = False
        opts.ba_refine_extra_params = False
        opts.random_seed = seed
        opts.multiple_models = False
        models = pycolmap.incremental_mapping(db, image_dir, work / "sparse", options=opts)
        stages.update(1)
        stages.set_postfix_str("scale")
        if not models:
            raise PavemapError(
                f"SfM failed: no reconstruction from {len(images)} images (too little texture or motion?)"
            )
        rec = max(models.values(), key=lambda r: r.num_reg_images())
        by_name = {img.name: img for img in rec.images.values()}
        N = len(images)
        registered = np.array([n in by_name for n in names])
        if registered.mean() < min_registered:
            raise PavemapError(
                f"SfM registered only {registered.sum()} of {N} images; need {min_registered:.0%} "
                "(try a higher frame rate or a sharper video)"
            )
        T_cw = np.full((N, 4, 4), np.nan)
        for i, n in enumerate(names):
            if registered[i]:
                cfw = by_name[n].cam_from_world()
                T = np.eye(4)
                T[:3, :4] = cfw.matrix()
                T_cw[i] = T
        reg = np.nonzero(registered)[0]
        T_wc = np.linalg.inv(T_cw[reg])  # (R, 4, 4) SfM world <- camera
        C = T_wc[:, :3, 3]
        R_wc = T_wc[:, :3, :3]
        P = np.array([p.xyz for p in rec.points3D.values()], dtype=np.float64).reshape(-1, 3)
        # "up": the cameras' mean -y axis with the component along the drive removed (the
        # mount's pitch tilts -y forward or back; the drive itself is near-level on average)
        up = -R_wc[:, :, 1].mean(0)
        _, _, Vt = np.linalg.svd(C - C.mean(0), full_matrices=False)
        along = Vt[0]
        up = up - (up @ along) * along if len(C) > 2 and np.ptp(C @ along) > 0 else up
        up /= np.linalg.norm(up)
        cand = _road_candidates(P, C, R_wc, K, camera.width, camera.height, up)
        heights, drive_over = _heights_below_path(P[cand], C, up)
        if drive_over.sum() < 10:
            raise PavemapError(
                f"SfM: only {int(drive_over.sum())} 3D points on the road under the driven path; cannot fix the scale"
            )
        h_sfm = float(np.median(heights[drive_over]))
        if not h_sfm > 0:
            raise PavemapError("SfM: the road points are not below the cameras")
        s = camera_height / h_sfm
        n = up
        spread = float(np.median(np.abs(heights[drive_over] - h_sfm)) / h_sfm)
        # metric z-up world: z = n, x = driving direction in the plane, origin under camera 0
        travel = C[-1] - C[0]
        x = travel - (travel @ n) * n
        if np.linalg.norm(x) < 1e-9:
            x = R_wc[0][:, 2] - (R_wc[0][:, 2] @ n) * n
        x /= np.linalg.norm(x)
        y = np.cross(n, x)
        A = np.stack([x, y, n])  # rows: new axes in SfM coordinates
        origin = C[0] - h_sfm * n
        out = np.full((N, 4, 4), np.nan)
        M = np.tile(np.eye(4), (len(reg), 1, 1))
        M[:, :3, :3] = A @ R_wc
        M[:, :3, 3] = s * (C - origin) @ A.T
        U, _, Vt = np.linalg.svd(M[:, :3, :3])
        M[:, :3, :3] = U @ Vt
        out[reg] = M
        pts = s * (P - origin) @ A.T
        info = {
            "registered": int(registered.sum()),
            "images": N,
            "points": len(P),
            "road_candidates": int(cand.sum()),
            "road_points_under_path": int(drive_over.sum()),
            "height_spread": spread,  # median |h - median h| / median h of those points
        }
        stages.update(1)
        stages.close()
        log.info("SfM: %s", info)
        return SfmResult(out, registered, float(s), int(drive_over.sum()), pts, info)
    finally:
        pycolmap.logging.minloglevel = old_level
        if own_tmp:
            shutil.rmtree(work, ignore_errors=True)
