"""Camera poses from plain video: COLMAP or the car's planar motion, made metric by the road (docs/sfm.md).

Steps (:func:`sfm_poses`):

0. Keyframes by parallax (:func:`pavemap.sfm.checks.select_keyframes`): frames of a stopped car are left out
   (posed between keyframes at the end). The ego vehicle (``ego_mask``) and what may move (``movers``: the
   segmenter's vehicles and people) are masked out of feature extraction.
1. COLMAP (:mod:`pavemap.sfm.colmap`): SIFT, sequential matching, incremental mapping with the known
   intrinsics, forward-motion initial pairs allowed; the largest model is kept.
2. The car's motion (:mod:`pavemap.sfm.parts`): the keyframes' path is cut at unregistered frames, heading
   jumps and teleports, the longest consistent part kept and every other frame named; steps off the car's
   heading are repaired onto it. Where COLMAP gives no usable path (none, too small, translations off the
   heading) the car's planar motion between consecutive frames replaces it (:mod:`pavemap.sfm.planar`); where
   COLMAP's path needed repairs or left keyframes unregistered, both are scored by the road and the better kept.
3. Axes and a first scale: world z = up, x = the driving direction, origin = the first camera's foot point;
   the scale from SfM's sparse road points under the path (:mod:`pavemap.sfm.sparse`) when there are some,
   else provisional.
4. The metric scale from the road (:func:`_set_scale`): each step's length from the road plane's image motion
   at the known camera height (:mod:`pavemap.sfm.steps`), checked by densely matched road points
   (:mod:`pavemap.sfm.scale`); a clip whose scale nothing could set is refused.
5. Sanity checks (:func:`pavemap.sfm.checks.check_sfm`): reprojection error, turns, step ratios, speed changes
   within ~1 g with frame times, a path that moves when its images do, the camera height along it.
6. What was measured goes into ``info``; :func:`sfm_poses_or_report` writes ``sfm.json`` / ``sfm.png``
   (:mod:`pavemap.sfm.report`) also when the clip is refused.
"""

from __future__ import annotations

import logging
import os
import shutil
import tempfile
from collections.abc import Callable
from pathlib import Path

import numpy as np

from pavemap.errors import PavemapError
from pavemap.geometry.road_height import camera_heights
from pavemap.sfm.checks import SfmChecks, check_sfm, select_keyframes
from pavemap.sfm.colmap import colmap_model, prepare_images
from pavemap.sfm.held_log import held_records, replay, warnings_of
from pavemap.sfm.parts import PartLimits, consistent_parts, repair_skids, step_flags
from pavemap.sfm.planar import planar_result
from pavemap.sfm.report import write_sfm_report
from pavemap.sfm.result import SfmRefusedError, SfmResult
from pavemap.sfm.scale import dense_rescale, road_relength
from pavemap.sfm.sparse import fill_between_keyframes, heights_below_path, road_candidates
from pavemap.types import Camera

log = logging.getLogger(__name__)




def sfm_poses(images: list[Path], camera: Camera, camera_height: float = 1.5, workdir: str | os.PathLike | None = None,
              overlap: int = 10, num_threads: int = 1, max_features: int = 8192, min_registered: float = 0.0,
              seed: int = 0, peak_threshold: float = 0.003, verbose: bool = False, ego_mask: np.ndarray | None = None,
              refine_intrinsics: bool = False, min_parallax: float = 0.002, init_min_tri_angle: float = 2.0,
              checks: SfmChecks | None = None, dense_scale: bool = True, road_steps: bool = True,
              times: np.ndarray | None = None, limits: PartLimits | None = None,
              method: str = "auto", movers: Callable[[Path], np.ndarray | None] | None = None) -> SfmResult:
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
    ``limits``: when a step breaks the path (:mod:`pavemap.sfm.parts`): the longest consistent part is kept and
    the frames left out are named in ``info["dropped"]``. ``method``: "auto" (COLMAP; where it gives no usable
    model: none, too small, or steps that do not follow the car's heading, the car's planar motion between
    consecutive frames instead, :mod:`pavemap.sfm.planar`), "colmap" (no fallback) or "planar" (no COLMAP).
    Raises :class:`~pavemap.sfm.result.SfmRefusedError` (a PavemapError holding what was measured) with a clear line
    when nothing usable is left or the kept part fails a check.
    """
    try:
        import pycolmap
    except ImportError as e:
        raise PavemapError(f"--poses sfm needs pycolmap: pip install 'pavemap[sfm]' ({e})") from None
    _check_inputs(images, camera, camera_height, ego_mask, times, method)
    checks = checks or SfmChecks(min_registered=min_registered)
    limits = limits or PartLimits()
    images = [Path(p) for p in images]
    keyframes = select_keyframes(images, min_parallax, ego_mask) if min_parallax > 0 else np.ones(len(images), bool)
    info: dict = {"images": len(images), "keyframes": int(keyframes.sum()), "camera_height_m": camera_height,
                  "keyframe_index": np.flatnonzero(keyframes).tolist()}
    # COLMAP logs every step at INFO to stderr, and its bundle adjustment a "Linear solver failure" warning each
    # time it retries a step with more damping (672 lines on a 47-frame clip): keep errors; what came of it is in
    # sfm.json and our own messages (verbose: everything)
    old_level = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = int(pycolmap.logging.ERROR) if verbose is False else 0
    own_tmp = workdir is None
    work = Path(tempfile.mkdtemp(prefix="pavemap-sfm-")) if own_tmp else Path(workdir)
    work.mkdir(parents=True, exist_ok=True)
    masked = ego_mask is not None and ego_mask.any()
    hint = "too little texture or motion?" if masked else "if the ego vehicle (bonnet) is in view, give --ego-mask"
    try:
        image_dir, all_names = prepare_images(images, work)
        names = [n for n, k in zip(all_names, keyframes, strict=True) if k]
        o = {"num_threads": num_threads, "max_features": max_features, "peak_threshold": peak_threshold,
             "overlap": overlap, "seed": seed, "init_min_tri_angle": init_min_tri_angle,
             "refine_intrinsics": refine_intrinsics, "min_share": max(checks.min_registered, 0.9),
             "max_focal_change": 0.05}
        if keyframes.sum() < limits.min_frames:
            raise PavemapError(f"the camera hardly moves: only {int(keyframes.sum())} of {len(images)} frames show "
                               f"parallax of {min_parallax:.1%} of the image width or more against the frame before "
                               f"(need {limits.min_frames}; a parked car, or a frame rate far above the motion)")
        masks = _mover_masks(movers, images, all_names, keyframes, ego_mask, work, info) if movers else None
        o["mask_dir"] = None if masks is None else work / "masks"
        rec = colmap_model(pycolmap, work, image_dir, names, camera, ego_mask, o) if method != "planar" else None
        res = _first_path(rec, method, images, all_names, keyframes, camera, camera_height, ego_mask, limits, hint,
                          info, masks)
        if "intrinsics" in o:
            res.info["intrinsics_refinement"] = o["intrinsics"]
        res = _scaled_best(res, method, images, keyframes, camera, camera_height, ego_mask, limits, road_steps,
                           dense_scale, hint, masks)
        res.info["checks"] = check_sfm(res.info, res.T_world_cam[res.registered, :3, 3], res.info.pop("_heights"),
                                       checks, hint, None if times is None else np.asarray(times)[res.registered])
        fill_between_keyframes(res, keyframes)
        res.info["registered"] = int(res.registered.sum())  # with the frames posed between keyframes
        res.info["status"] = "ok"
        log.info("SfM: %s", {k: v for k, v in res.info.items() if not k.startswith("_")})
        return res
    except PavemapError as e:
        info.update(status="refused", reason=str(e))
        raise SfmRefusedError(str(e), info) from None
    finally:
        pycolmap.logging.minloglevel = old_level
        if own_tmp:
            shutil.rmtree(work, ignore_errors=True)


def _scaled_best(res: SfmResult, method: str, images: list[Path], keyframes: np.ndarray, camera: Camera,
                 camera_height: float, ego_mask: np.ndarray | None, limits: PartLimits, road_steps: bool,
                 dense_scale: bool, hint: str, masks: list[Path | None] | None) -> SfmResult:
    """``res`` made metric, or (auto, COLMAP's path repaired or incomplete) the better of it and the car's planar
    motion. Only the kept path's messages reach the log; the other's warnings are kept in
    ``info["alternatives"]["warnings_of_the_path_not_kept"]`` (:mod:`pavemap.sfm.held_log`)."""
    with held_records() as said:
        _set_scale(res, images, camera, camera_height, ego_mask, road_steps, dense_scale, hint)
    if method == "auto" and res.info.get("method") == "pycolmap SfM" and (
            res.info["steps"]["repaired"] or res.registered[keyframes].sum() < keyframes.sum()):
        with held_records() as said_alt:
            best = _better_of(res, images, keyframes, camera, camera_height, ego_mask, limits, road_steps,
                              dense_scale, hint, masks)
        if best is not res:
            said, said_alt, res = said_alt, said, best
        res.info["alternatives"]["warnings_of_the_path_not_kept"] = warnings_of(said_alt)
    replay(said)
    return res


def _check_inputs(images: list[Path], camera: Camera, camera_height: float, ego_mask: np.ndarray | None,
                  times: np.ndarray | None, method: str) -> None:
    """One-line errors for arguments :func:`sfm_poses` cannot work with, before any SfM work."""
    if len(images) < 3:
        raise PavemapError(f"SfM needs at least 3 images, got {len(images)}")
    if camera_height <= 0:
        raise PavemapError(f"camera height must be positive metres, got {camera_height}")
    if ego_mask is not None and ego_mask.shape != (camera.height, camera.width):
        raise PavemapError(f"ego mask is {ego_mask.shape[1]}x{ego_mask.shape[0]}, camera {camera.name} is "
                           f"{camera.width}x{camera.height}")
    if times is not None and len(times) != len(images):
        raise PavemapError(f"SfM: {len(times)} frame times for {len(images)} images")
    if method not in ("auto", "colmap", "planar"):
        raise PavemapError(f"SfM method must be auto, colmap or planar, got {method!r}")


def _first_path(rec, method: str, images: list[Path], names: list[str], keyframes: np.ndarray,  # noqa: ANN001
                camera: Camera, camera_height: float, ego_mask: np.ndarray | None, limits: PartLimits, hint: str,
                info: dict, masks: list[Path | None] | None) -> SfmResult:
    """COLMAP's model ``rec`` made metric, or (``method`` auto / planar) the car's planar motion where COLMAP gave
    no usable path: none, too few frames, or translations off the car's heading."""
    try:
        if method == "planar":
            raise PavemapError("planar motion asked for")
        if rec is None:
            raise PavemapError(f"SfM failed: no reconstruction from {int(keyframes.sum())} keyframes ({hint})")
        res = _metric_result(rec, names, keyframes, camera, camera_height, limits, hint, info)
        info["method"] = "pycolmap SfM"
        if info.get("translations_rejected"):
            raise PavemapError("SfM's steps point off the car's heading in most places (its translations are wrong)")
        return res
    except PavemapError as e:
        if method == "colmap":
            raise
        if method == "auto":
            log.warning("SfM: %s; following the car's planar motion instead", e)
        info["sfm_failure"] = str(e)
        return planar_result(images, keyframes, camera, camera_height, ego_mask, limits.min_frames, info, masks=masks)


def _set_scale(res: SfmResult, images: list[Path], camera: Camera, camera_height: float,
               ego_mask: np.ndarray | None, road_steps: bool, dense_scale: bool, hint: str) -> None:
    """The metric scale of ``res`` (in place): the road's step lengths where they measured most of the path,
    else the dense road points, else the sparse road points; stop when none of them could set it.

    With the road's scale set, the dense ground points only measure the heights for the checks (on the KITTI
    sample they moved the road's scale 4 % away from what they read with the true poses)."""
    provisional = res.info["scale_source"].startswith("provisional")
    # a path without any scale of its own takes the road's wherever a quarter of its steps were measured
    scaled = road_steps and road_relength(res, images, camera, camera_height, ego_mask,
                                          min_share=0.25 if provisional else 0.5)
    if scaled:
        res.info["scale_source"] = "the road's step lengths"
    if dense_scale:
        dense_rescale(res, images, camera, camera_height, ego_mask, apply=not scaled)
        if not scaled and res.info.get("dense_scale", {}).get("applied"):
            res.info["scale_source"] = "dense road points under the path"
    if res.info["scale_source"].startswith("provisional"):
        steps = res.info.get("road_steps", {})
        dense = res.info.get("dense_scale", {})
        raise PavemapError(
            f"SfM: cannot fix the metric scale: {res.info['road_points_under_path']} sparse 3D points on the road "
            f"under the path, {steps.get('measured', 0)} of {steps.get('steps', 0)} steps measured on the road, "
            f"dense road matching: {dense.get('reason') or 'not run'} ({hint})")


def _mover_masks(movers: Callable[[Path], np.ndarray | None], images: list[Path], names: list[str],
                 keyframes: np.ndarray, ego: np.ndarray | None, work: Path, info: dict) -> list[Path | None]:
    """``work/masks/<name>.png`` for each keyframe (COLMAP's per-image masks: white = match here; black = the
    ego vehicle and what ``movers`` marks), the list of them by image (None for frames that are not keyframes),
    and ``info["movers"]``: how many frames had masks and the mean share masked."""
    from PIL import Image

    (work / "masks").mkdir(exist_ok=True)
    out: list[Path | None] = [None] * len(images)
    shares = []
    for i in np.flatnonzero(keyframes):
        m = movers(images[i])
        bad = np.zeros(Image.open(images[i]).size[::-1], bool) if m is None else m.copy()
        if m is not None:
            shares.append(float(m.mean()))
        if ego is not None and ego.shape == bad.shape:
            bad |= ego
        out[i] = work / "masks" / f"{names[i]}.png"
        Image.fromarray(np.where(bad, 0, 255).astype(np.uint8)).save(out[i])
    info["movers"] = {"frames_masked": len(shares), "mean_share": round(float(np.mean(shares)), 4) if shares else 0.0}
    return out


def _road_measured(res: SfmResult) -> int:
    """How many of a path's steps the road's image motion measured (trusted): how well the road, the one thing
    both methods are judged on without truth, agrees with the path's rotations and directions, and over how
    much of the clip. A count, not a share: a path that keeps more frames with steps the road confirms is the
    better one."""
    return int((res.info.get("road_steps") or {}).get("measured", 0))


def _better_of(res: SfmResult, images: list[Path], keyframes: np.ndarray, camera: Camera, camera_height: float,
               ego_mask: np.ndarray | None, limits: PartLimits, road_steps: bool, dense_scale: bool,
               hint: str, masks: list[Path | None] | None = None) -> SfmResult:
    """COLMAP's path needed steps repaired onto the car's heading, or left keyframes unregistered: the car's
    planar motion is tried too and the path with more steps the road measured is kept (COLMAP on a tie);
    ``info["alternatives"]`` says what each scored. (A synthetic stop-and-go: COLMAP 2.2 % off its true path
    after three repairs, the planar motion 0.9 %.)"""
    base = {k: v for k, v in res.info.items()
            if k in ("images", "keyframes", "camera_height_m", "keyframe_index", "movers")}
    try:
        alt = planar_result(images, keyframes, camera, camera_height, ego_mask, limits.min_frames, dict(base),
                            masks=masks)
        _set_scale(alt, images, camera, camera_height, ego_mask, road_steps, dense_scale, hint)
    except PavemapError as e:
        res.info["alternatives"] = {"planar motion": f"refused: {e}"}
        return res
    scores = {"pycolmap SfM": _road_measured(res), "planar motion": _road_measured(alt)}
    best = alt if scores["planar motion"] > scores["pycolmap SfM"] else res
    why = ("COLMAP's path had steps repaired onto the car's heading" if res.info["steps"]["repaired"] else
           f"COLMAP registered {res.info.get('registered_by_sfm', int(res.registered.sum()))} of "
           f"{int(keyframes.sum())} keyframes")
    best.info["alternatives"] = {"road_measured_steps": scores, "why": why}
    if best is alt:
        best.info["sfm_failure"] = f"{why}; the road measures more of the planar motion's steps"
        best.info["registered_by_sfm"] = res.info.get("registered_by_sfm")
    return best


def _model_poses(rec, names: list[str], keyframes: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray,
                                                                          np.ndarray]:
    """SfM-frame camera-to-world poses (N, 4, 4) (NaN where not registered), ``registered`` (N,) bool (keyframes
    only), K (3, 3) (pixel-centre convention) and the model's points (P, 3)."""
    by_name = {img.name: img for img in rec.images.values()}
    registered = np.array([n in by_name for n in names]) & keyframes
    T_wc = np.full((len(names), 4, 4), np.nan)
    for i in np.flatnonzero(registered):
        T = np.eye(4)
        T[:3, :4] = by_name[names[i]].cam_from_world().matrix()
        T_wc[i] = np.linalg.inv(T)
    cam = rec.cameras[next(iter(by_name.values())).camera_id] if by_name else None
    fx, fy, cx, cy = (float(v) for v in cam.params[:4]) if cam is not None else (np.nan,) * 4
    K = np.array([[fx, 0.0, cx - 0.5], [0.0, fy, cy - 0.5], [0.0, 0.0, 1.0]])
    P = np.array([p.xyz for p in rec.points3D.values()], dtype=np.float64).reshape(-1, 3)
    return T_wc, registered, K, P


def _up(T_wc: np.ndarray, min_turn_deg: float = 30.0) -> np.ndarray:
    """The road's "up" (3,) in the SfM frame from registered poses (R, 4, 4).

    A car turns about the road's normal, which is fixed in the camera (the mount does not move): where the
    path turns by ``min_turn_deg`` or more, up is the camera-frame axis that all the rotations map to one world
    direction (the least-squares common axis; it does not need the translations, which forward-motion SfM gets
    wrong first). On a straighter drive: the cameras' mean -y axis with the component along the drive removed
    (the mount's pitch tilts -y forward or back; the drive is near-level on average)."""
    C, R_wc = T_wc[:, :3, 3], T_wc[:, :3, :3]
    f = R_wc[:, :, 2]
    turned = np.degrees(np.arccos(np.clip(f @ f.T, -1.0, 1.0))).max() if len(f) > 1 else 0.0
    if turned >= min_turn_deg:
        dev = R_wc - R_wc.mean(0)
        w, V = np.linalg.eigh(np.einsum("kji,kjl->il", dev, dev))  # sum_k dev_kᵀ dev_k
        n_cam = V[:, 0] if V[1, 0] < 0 else -V[:, 0]  # up is the camera's -y side
        up = (R_wc @ n_cam).mean(0)
        return up / np.linalg.norm(up)
    up = -R_wc[:, :, 1].mean(0)
    _, _, Vt = np.linalg.svd(C - C.mean(0), full_matrices=False)
    along = Vt[0]
    up = up - (up @ along) * along if len(C) > 2 and np.ptp(C @ along) > 0 else up
    return up / np.linalg.norm(up)


def _keep_consistent(T_wc: np.ndarray, registered: np.ndarray, keyframes: np.ndarray, limits: PartLimits,
                     info: dict) -> np.ndarray:
    """``registered`` narrowed to the longest consistent part of the keyframes' path and the steps that skid
    repaired onto the car's heading (in place in ``T_wc``) (:mod:`pavemap.sfm.parts`). ``info["dropped"]``
    {frame: reason}, ``info["parts"]`` and ``info["steps"]`` say what was left out, repaired and why."""
    kf = np.flatnonzero(keyframes)
    reg_kf = registered[kf]
    up = _up(T_wc[registered])
    keep_kf, dropped, figures = consistent_parts(reg_kf, np.nan_to_num(T_wc[kf, :3, 3]),
                                                 np.nan_to_num(T_wc[kf, :3, 2]), up, limits)
    info["dropped"] = {int(kf[i]): why for i, why in sorted(dropped.items())}
    info["parts"] = [[int(kf[a]), int(kf[b]), bool(k)] for a, b, k in figures["parts"]]
    out = np.zeros_like(registered)
    out[kf[keep_kf]] = True
    if out.sum() < limits.min_frames:
        longest = "none" if not out.any() else f"frames {kf[keep_kf][0]}-{kf[keep_kf][-1]}"
        raise PavemapError(f"SfM: no consistent part of at least {limits.min_frames} keyframes to keep (longest: "
                           f"{longest}, {int(out.sum())} keyframes; {int(reg_kf.sum())} of {len(kf)} registered)")
    kept = np.flatnonzero(out)
    flags = step_flags(T_wc[kept, :3, 3], T_wc[kept, :3, 2], up, limits)
    moving = np.array([x is not None for x in flags["skid_deg"]], dtype=bool)
    if flags["skids"].sum() > 0.5 * max(1, moving.sum()):
        # most steps off the heading: SfM's translations are wrong as a whole, not here and there
        flags["skids"] = np.ones_like(flags["skids"])
        info["translations_rejected"] = True
    T_wc[kept, :3, 3] = repair_skids(T_wc[kept, :3, 3], T_wc[kept, :3, 2], up, flags["skids"],
                                     flags["mount_yaw_deg"], flags["reverse"])
    if flags["reverse"]:
        log.warning("SfM: the camera moves backwards along its view in most steps: are the frames numbered in "
                    "reverse? (mapped as given: a reversing car)")
    info["steps"] = {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in flags.items() if k != "why"}
    info["steps"]["repaired"] = np.flatnonzero(flags["skids"]).tolist()  # step k: kept frame k -> k+1
    return out


def _metric_result(rec, names: list[str], keyframes: np.ndarray, camera: Camera, camera_height: float,
                   limits: PartLimits, hint: str, info: dict) -> SfmResult:
    """Keep the longest consistent part, scale it by the camera height, turn it z-up, and pack the result.

    The scale here comes from the sparse road points under the path; where there are too few of them (SIFT
    rarely lands on smooth asphalt) it is provisional and the road's step lengths or the dense road points
    set it afterwards (:func:`sfm_poses`); ``info["scale_source"]`` says which."""
    T_all, registered, K, P = _model_poses(rec, names, keyframes)
    info.update(registered_by_sfm=int(registered.sum()), points=len(P),
                reproj_px=float(rec.compute_mean_reprojection_error()))
    info["_poses_sfm"] = T_all
    if registered.sum() < 3:
        raise PavemapError(f"SfM registered only {int(registered.sum())} of {int(keyframes.sum())} keyframes "
                           f"({hint})")
    registered = _keep_consistent(T_all, registered, keyframes, limits, info)
    reg = np.flatnonzero(registered)
    T_wc = T_all[reg]
    C, R_wc = T_wc[:, :3, 3], T_wc[:, :3, :3]
    up = _up(T_wc)
    cand = road_candidates(P, C, R_wc, K, camera.width, camera.height, up)
    heights, drive_over = heights_below_path(P[cand], C, up)
    info.update(road_candidates=int(cand.sum()), road_points_under_path=int(drive_over.sum()))
    if drive_over.sum() >= 3 and np.median(heights[drive_over]) > 0 and not info.get("translations_rejected"):
        h_sfm = float(np.median(heights[drive_over]))
        info["scale_source"] = "sparse road points under the path"
        info["height_spread"] = float(np.median(np.abs(heights[drive_over] - h_sfm)) / h_sfm)
    else:
        # a provisional scale: a step of the median length taken as 5 m (a car at 36 km/h, 2 Hz); the road's
        # step lengths replace it, and without them the import stops (sfm_poses)
        steps = np.linalg.norm(np.diff(C, axis=0), axis=1)
        h_sfm = camera_height * float(np.median(steps[steps > 0])) / 5.0 if (steps > 0).any() else 1.0
        info["scale_source"] = ("provisional (SfM's translations rejected)" if info.get("translations_rejected")
                                else "provisional (too few sparse road points)")
    s = camera_height / h_sfm
    n = up
    # metric z-up world: z = n, x = driving direction in the plane, origin under camera 0
    travel = C[-1] - C[0]
    x = travel - (travel @ n) * n
    if np.linalg.norm(x) < 1e-9:
        x = R_wc[0][:, 2] - (R_wc[0][:, 2] @ n) * n
    x /= np.linalg.norm(x)
    A = np.stack([x, np.cross(n, x), n])  # rows: new axes in SfM coordinates
    origin = C[0] - h_sfm * n
    out = np.full((len(names), 4, 4), np.nan)
    M = np.tile(np.eye(4), (len(reg), 1, 1))
    M[:, :3, :3] = A @ R_wc
    M[:, :3, 3] = s * (C - origin) @ A.T
    U, _, Vt = np.linalg.svd(M[:, :3, :3])
    M[:, :3, :3] = U @ Vt
    out[reg] = M
    # the dropped parts in the same frame, for the diagnosis figure only
    moved = np.isfinite(T_all[:, 0, 0])
    info["_poses_sfm"] = np.full_like(T_all, np.nan)
    info["_poses_sfm"][moved, :3, 3] = s * (T_all[moved, :3, 3] - origin) @ A.T
    pts = s * (P - origin) @ A.T
    info.update(registered=int(registered.sum()), images=len(names), keyframes=int(keyframes.sum()))
    info["K_refined"] = {k: round(float(v), 2) for k, v in zip(("fx", "fy", "cx", "cy"),
                                                               (K[0, 0], K[1, 1], K[0, 2], K[1, 2]), strict=True)}
    road = pts[cand][drive_over]
    info["_heights"] = camera_heights(road, M[:, :3, 3], np.array([0.0, 0.0, 1.0]), lateral=1.5 * camera_height)
    return SfmResult(out, registered, float(s), int(drive_over.sum()), pts, info, K)


def sfm_poses_or_report(out: Path, images: list[Path], camera: Camera, **kw: object) -> SfmResult:
    """:func:`sfm_poses`; on a refusal ``sfm.json`` / ``sfm.png`` go into ``out`` before the one-line error (what
    was registered, what was dropped and why), so a refused clip still leaves its diagnosis."""
    try:
        return sfm_poses(images, camera, **kw)
    except SfmRefusedError as e:
        Path(out).mkdir(parents=True, exist_ok=True)
        files = write_sfm_report(e.info, out)
        raise PavemapError(f"{e}. What SfM measured: {', '.join(str(f) for f in files)}") from None


def report_result(res: SfmResult | None, out: Path) -> None:
    """The kept path's ``sfm.json`` / ``sfm.png`` (nothing when poses were given; the import command names them)."""
    if res is not None:
        write_sfm_report(res.info, out, res.T_world_cam, res.registered, scale=res.scale)


def frames_by_motion(images: list[Path], min_parallax: float, ego_mask: np.ndarray | None = None) -> np.ndarray:
    """(N,) bool: the frames SfM would take as keyframes at ``min_parallax`` (share of the image width the
    scene moves between kept frames; :func:`pavemap.sfm.checks.select_keyframes`), for choosing a video's
    frame rate from its motion."""
    return select_keyframes(images, min_parallax, ego_mask)
