"""Camera poses from plain video: incremental SfM with pycolmap, metric scale from the mount height.

Steps (:func:`sfm_poses`):

0. Keyframes by parallax (:func:`pavemap.sfm.checks.select_keyframes`): frames of a stopped
   car are left out. The ego vehicle (``ego_mask``, :mod:`pavemap.io.egomask`) is masked out of
   feature extraction: features on a bonnet move with the camera and pull SfM to zero motion.
1. SIFT features, sequential matching (video order, with loop-free overlap), incremental
   mapping with the known intrinsics held fixed (PINHOLE, one camera). Forward motion is the
   normal case for a car: the initial pair may be along the viewing direction and need only a
   small triangulation angle (COLMAP's defaults reject exactly such pairs). With
   ``refine_intrinsics`` (nominal intrinsics) a final bundle adjustment refines focal length and
   principal point. The largest model is kept; images it could not register are left out.
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
5. Sanity checks (:func:`pavemap.sfm.checks.check_sfm`): registered share, reprojection error,
   smoothness of the path (turns, step ratios and, with frame times, speed changes within a car's ~1 g)
   and a constant camera height along it, else a clear error.
"""

from __future__ import annotations

import logging
import os
import shutil
import tempfile
from pathlib import Path

import numpy as np

from pavemap.errors import PavemapError
from pavemap.geometry.road_height import camera_heights
from pavemap.sfm.checks import SfmChecks, check_sfm, select_keyframes
from pavemap.sfm.result import SfmResult
from pavemap.sfm.scale import dense_rescale, road_relength
from pavemap.types import Camera

log = logging.getLogger(__name__)


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


def _colmap_model(pycolmap, work: Path, image_dir: Path, names: list[str], camera: Camera, mask: np.ndarray | None,
                  o: dict):
    """Features (masked), sequential matching and incremental mapping → the largest model, or None."""
    db = work / "database.db"
    if db.exists():
        db.unlink()
    K = camera.K
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "PINHOLE"
    reader.camera_params = f"{K[0, 0]},{K[1, 1]},{K[0, 2] + 0.5},{K[1, 2] + 0.5}"  # COLMAP: pixel corner origin
    if mask is not None and mask.any():
        from pavemap.io.egomask import colmap_mask

        reader.camera_mask_path = str(colmap_mask(mask, work / "ego_mask.png"))
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = o["num_threads"]
    extraction.sift.max_num_features = o["max_features"]
    # road surfaces are low-contrast: a lower peak threshold keeps their (few) features
    extraction.sift.peak_threshold = o["peak_threshold"]
    extraction.use_gpu = False
    pycolmap.extract_features(work / "database.db", image_dir, image_names=names,
                              camera_mode=pycolmap.CameraMode.SINGLE, reader_options=reader,
                              extraction_options=extraction, device=pycolmap.Device.cpu)
    pairing = pycolmap.SequentialPairingOptions()
    pairing.overlap = o["overlap"]
    pairing.quadratic_overlap = True
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = o["num_threads"]
    matching.use_gpu = False
    pycolmap.match_sequential(db, matching_options=matching, pairing_options=pairing, device=pycolmap.Device.cpu)
    opts = pycolmap.IncrementalPipelineOptions()
    opts.num_threads = o["num_threads"]
    opts.ba_refine_focal_length = False  # refined once at the end, if at all: early refinement drifts
    opts.ba_refine_principal_point = False
    opts.ba_refine_extra_params = False
    opts.random_seed = o["seed"]
    opts.multiple_models = True  # a bad first model must not end the search; the largest is kept
    # a car moves along its viewing direction: accept forward-motion initial pairs with small angles
    opts.mapper.init_max_forward_motion = 1.0
    rec = None
    # a small initial angle starts forward motion; if its model stays small, ask for a wider pair
    for angle in (o["init_min_tri_angle"], 2 * o["init_min_tri_angle"], 4 * o["init_min_tri_angle"]):
        opts.mapper.init_min_tri_angle = angle
        shutil.rmtree(work / "sparse", ignore_errors=True)
        models = pycolmap.incremental_mapping(db, image_dir, work / "sparse", options=opts)
        best = max(models.values(), key=lambda r: r.num_reg_images()) if models else None
        if best is not None and (rec is None or best.num_reg_images() > rec.num_reg_images()):
            rec = best
        if rec is not None and rec.num_reg_images() >= o["min_share"] * len(names):
            break
        log.info("SfM: init angle %.1f° registered %d of %d; retrying", angle,
                 0 if rec is None else rec.num_reg_images(), len(names))
    if rec is None:
        return None
    if o["refine_intrinsics"]:
        rec = _refine_intrinsics(pycolmap, rec, o)
    return rec


def _refine_intrinsics(pycolmap, rec, o: dict):
    """Bundle adjustment with focal length and principal point free, on a copy; adopted only when sane.

    Forward motion constrains the focal length weakly (it trades against depth), so a refinement that
    moves the focal length by more than ``max_focal_change`` (or the principal point by more than 5 % of
    the image) or does not lower the reprojection error is reported and rejected.
    """
    trial = pycolmap.Reconstruction(rec)
    ba = pycolmap.BundleAdjustmentOptions()
    ba.refine_focal_length = True
    ba.refine_principal_point = True
    ba.refine_extra_params = False
    pycolmap.bundle_adjustment(trial, ba)
    c0 = next(iter(rec.cameras.values()))
    c1 = next(iter(trial.cameras.values()))
    p0, p1 = np.asarray(c0.params[:4], float), np.asarray(c1.params[:4], float)
    e0, e1 = rec.compute_mean_reprojection_error(), trial.compute_mean_reprojection_error()
    df = abs(p1[0] / p0[0] - 1.0)
    dpp = float(np.abs(p1[2:4] - p0[2:4]).max()) / max(c0.width, c0.height)
    ok = df <= o["max_focal_change"] and dpp <= 0.05 and e1 <= e0
    o["intrinsics"] = {"fx": round(p1[0], 2), "fy": round(p1[1], 2), "cx": round(p1[2] - 0.5, 2),
                       "cy": round(p1[3] - 0.5, 2), "focal_change": round(df, 4), "reproj_px": [round(e0, 3),
                       round(e1, 3)], "adopted": bool(ok)}
    log.info("SfM intrinsics refinement: %s", o["intrinsics"])
    return trial if ok else rec


def _prepare_images(images: list[Path], work: Path) -> tuple[Path, list[str]]:
    """One folder pycolmap can read and the image names in it (links when the images are spread out)."""
    folders = {p.parent.resolve() for p in images}
    if len(folders) == 1:
        return folders.pop(), [p.name for p in images]
    image_dir = work / "images"
    image_dir.mkdir(exist_ok=True)
    names = []
    for i, p in enumerate(images):
        name = f"{i:06d}{p.suffix.lower()}"
        if not (image_dir / name).exists():
            os.symlink(p.resolve(), image_dir / name)
        names.append(name)
    return image_dir, names


def sfm_poses(images: list[Path], camera: Camera, camera_height: float = 1.5, workdir: str | os.PathLike | None = None,
              overlap: int = 10, num_threads: int = 1, max_features: int = 8192, min_registered: float = 0.6,
              seed: int = 0, peak_threshold: float = 0.003, verbose: bool = False, ego_mask: np.ndarray | None = None,
              refine_intrinsics: bool = False, min_parallax: float = 0.002, init_min_tri_angle: float = 2.0,
              checks: SfmChecks | None = None, dense_scale: bool = True, road_steps: bool = True,
              times: np.ndarray | None = None) -> SfmResult:
    """Metric z-up camera-to-world poses (N, 4, 4) for ``images`` (video order) of one ``camera``.

    ``ego_mask`` (H, W) bool, True on the ego vehicle: no features there. ``refine_intrinsics``: the
    camera's K is nominal; refine focal length and principal point (``info["K_refined"]``).
    ``min_parallax``: keyframe threshold (share of the width, 0 = every frame). ``checks``: limits of
    the sanity checks (``min_registered`` overrides its share). ``road_steps``: each step's length,
    and so the metric scale, from the road's image motion (:mod:`pavemap.sfm.steps`; forward-motion
    SfM drifts in scale along a clip). ``dense_scale``: the cameras' heights over densely matched road
    points (:mod:`pavemap.sfm.scale`; sparse SIFT rarely lands on asphalt) for the checks, and the
    scale from them where the road's steps could not set it. ``times`` (N,) s of the images, when known
    (a video's frame rate): the path's speed changes are checked too (``SfmChecks.max_accel_mps2``).
    Raises PavemapError with a clear line when SfM fails or its result fails a check.
    """
    try:
        import pycolmap
    except ImportError as e:
        raise PavemapError(f"--poses sfm needs pycolmap: pip install 'pavemap[sfm]' ({e})") from None
    if len(images) < 3:
        raise PavemapError(f"SfM needs at least 3 images, got {len(images)}")
    if camera_height <= 0:
        raise PavemapError(f"camera height must be positive metres, got {camera_height}")
    if ego_mask is not None and ego_mask.shape != (camera.height, camera.width):
        raise PavemapError(f"ego mask is {ego_mask.shape[1]}x{ego_mask.shape[0]}, camera {camera.name} is "
                           f"{camera.width}x{camera.height}")
    if times is not None and len(times) != len(images):
        raise PavemapError(f"SfM: {len(times)} frame times for {len(images)} images")
    checks = checks or SfmChecks(min_registered=min_registered)
    images = [Path(p) for p in images]
    keyframes = select_keyframes(images, min_parallax, ego_mask) if min_parallax > 0 else np.ones(len(images), bool)
    # COLMAP logs every step at INFO to stderr; keep warnings, report progress ourselves
    old_level = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = int(pycolmap.logging.WARNING) if verbose is False else 0
    own_tmp = workdir is None
    work = Path(tempfile.mkdtemp(prefix="pavemap-sfm-")) if own_tmp else Path(workdir)
    work.mkdir(parents=True, exist_ok=True)
    masked = ego_mask is not None and ego_mask.any()
    hint = "too little texture or motion?" if masked else "if the ego vehicle (bonnet) is in view, give --ego-mask"
    try:
        image_dir, all_names = _prepare_images(images, work)
        names = [n for n, k in zip(all_names, keyframes, strict=True) if k]
        o = {"num_threads": num_threads, "max_features": max_features, "peak_threshold": peak_threshold,
             "overlap": overlap, "seed": seed, "init_min_tri_angle": init_min_tri_angle,
             "refine_intrinsics": refine_intrinsics, "min_share": max(checks.min_registered, 0.9),
             "max_focal_change": 0.05}
        rec = _colmap_model(pycolmap, work, image_dir, names, camera, ego_mask, o)
        if rec is None:
            raise PavemapError(f"SfM failed: no reconstruction from {len(names)} keyframes ({hint})")
        res = _metric_result(rec, all_names, keyframes, camera, camera_height, checks, hint)
        if "intrinsics" in o:
            res.info["intrinsics_refinement"] = o["intrinsics"]
        # the road's step lengths set the scale where they measured most of the path; the dense ground
        # points then only measure the heights for the checks (on the KITTI sample, with the road's scale
        # already set, they moved it 4 % away from what they read with the true poses)
        scaled = road_steps and road_relength(res, images, camera, camera_height, ego_mask)
        if dense_scale:
            dense_rescale(res, images, camera, camera_height, ego_mask, apply=not scaled)
        res.info["checks"] = check_sfm(res.info, res.T_world_cam[res.registered, :3, 3], res.info.pop("_heights"),
                                       checks, hint, None if times is None else np.asarray(times)[res.registered])
        _fill_between_keyframes(res, keyframes)
        log.info("SfM: %s", res.info)
        return res
    finally:
        pycolmap.logging.minloglevel = old_level
        if own_tmp:
            shutil.rmtree(work, ignore_errors=True)


def _metric_result(rec, names: list[str], keyframes: np.ndarray, camera: Camera, camera_height: float,
                   checks: SfmChecks, hint: str) -> SfmResult:
    """Scale the model by the camera height, turn it z-up, check it, and pack the result."""
    by_name = {img.name: img for img in rec.images.values()}
    N = len(names)
    registered = np.array([n in by_name for n in names]) & keyframes
    n_key = int(keyframes.sum())
    if registered.sum() < max(3, checks.min_registered * n_key):
        raise PavemapError(f"SfM registered only {int(registered.sum())} of {n_key} keyframes; need "
                           f"{checks.min_registered:.0%} ({hint})")
    cam = rec.cameras[next(iter(by_name.values())).camera_id]
    fx, fy, cx, cy = (float(v) for v in cam.params[:4])
    K = np.array([[fx, 0.0, cx - 0.5], [0.0, fy, cy - 0.5], [0.0, 0.0, 1.0]])
    T_cw = np.full((N, 4, 4), np.nan)
    for i, n in enumerate(names):
        if registered[i]:
            T = np.eye(4)
            T[:3, :4] = by_name[n].cam_from_world().matrix()
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
    if drive_over.sum() < 3:
        raise PavemapError(f"SfM: only {int(drive_over.sum())} 3D points on the road under the driven path; "
                           f"cannot fix the scale ({hint})")
    h_sfm = float(np.median(heights[drive_over]))
    if not h_sfm > 0:
        raise PavemapError(f"SfM: the road points are not below the cameras ({hint})")
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
        "keyframes": n_key,
        "points": len(P),
        "reproj_px": float(rec.compute_mean_reprojection_error()),
        "road_candidates": int(cand.sum()),
        "road_points_under_path": int(drive_over.sum()),
        "height_spread": spread,  # median |h - median h| / median h of those points
        "K_refined": {"fx": round(fx, 2), "fy": round(fy, 2), "cx": round(cx - 0.5, 2), "cy": round(cy - 0.5, 2)},
    }
    road = pts[cand][drive_over]
    info["_heights"] = camera_heights(road, M[:, :3, 3], np.array([0.0, 0.0, 1.0]), lateral=1.5 * camera_height)
    return SfmResult(out, registered, float(s), int(drive_over.sum()), pts, info, K)


SFM_REPORT = "sfm.json"


def write_sfm_report(res: SfmResult | None, out: Path) -> Path | None:
    """``out/sfm.json``: what SfM measured and checked (registered frames, intrinsics, the sanity checks'
    figures, each step's length by SfM and by the road, the dense points' heights) beside the sequence it made.
    Nothing without an SfM result (poses given)."""
    from pavemap.io.atomic import atomic_write_json

    if res is None:
        return None
    info = {k: v for k, v in res.info.items() if not k.startswith("_")}
    return atomic_write_json(Path(out) / SFM_REPORT, {"scale_m_per_unit": res.scale, **info})


def _fill_between_keyframes(res: SfmResult, keyframes: np.ndarray) -> None:
    """Poses of frames that were not keyframes (the car hardly moved), interpolated in place.

    Position linearly and rotation by slerp between the registered keyframes either side (by frame
    number); frames outside the registered span stay unregistered. ``info["interpolated"]`` counts them.
    """
    from scipy.spatial.transform import Rotation, Slerp

    reg = np.flatnonzero(res.registered)
    todo = [i for i in np.flatnonzero(~keyframes) if reg.size >= 2 and reg[0] < i < reg[-1]]
    if todo:
        T = res.T_world_cam[reg]
        slerp = Slerp(reg.astype(float), Rotation.from_matrix(T[:, :3, :3]))
        for i in todo:
            res.T_world_cam[i] = np.eye(4)
            res.T_world_cam[i, :3, :3] = slerp([float(i)]).as_matrix()[0]
            res.T_world_cam[i, :3, 3] = [np.interp(i, reg, T[:, k, 3]) for k in range(3)]
            res.registered[i] = True
    res.info["interpolated"] = len(todo)
