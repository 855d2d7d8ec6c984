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
from pavemap.sfm.checks import SfmChecks, check_sfm, select_keyframes
from pavemap.sfm.colmap import colmap_model, prepare_images
from pavemap.sfm.colmap_path import metric_result
from pavemap.sfm.held_log import held_records, replay, warnings_of
from pavemap.sfm.parts import PartLimits
from pavemap.sfm.planar import planar_result
from pavemap.sfm.report import write_sfm_report
from pavemap.sfm.result import SfmRefusedError, SfmResult
from pavemap.sfm.scale import dense_rescale, road_relength
from pavemap.sfm.sparse import fill_between_keyframes
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

        def model(kf: np.ndarray):  # noqa: ANN202  COLMAP's model of the keyframes kf (N,) bool
            return colmap_model(pycolmap, work, image_dir, [n for n, k in zip(all_names, kf, strict=True) if k],
                                camera, ego_mask, o)

        res, keyframes = _first_path(model, method, images, all_names, keyframes, camera, camera_height, ego_mask,
                                     limits, hint, info, masks)
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


RETRY_PARALLAX = 0.01  # share of the image width: the keyframes of COLMAP's second try
_INPUT_KEYS = ("images", "keyframes", "camera_height_m", "keyframe_index", "movers")  # what a path's info starts from


def _first_path(model: Callable[[np.ndarray], object], method: str, images: list[Path], names: list[str],
                keyframes: np.ndarray, camera: Camera, camera_height: float, ego_mask: np.ndarray | None,
                limits: PartLimits, hint: str, info: dict, masks: list[Path | None] | None
                ) -> tuple[SfmResult, np.ndarray]:
    """COLMAP's model of the keyframes made metric, or (``method`` auto / planar) the car's planar motion where
    COLMAP gave no usable path: none, too few frames, or translations off the car's heading; and the keyframes
    (N,) bool the path has. In auto, a failed COLMAP is tried once more on keyframes thinned to
    ``RETRY_PARALLAX`` first: a car creeping in a queue (0.2-0.3 m steps at 2 Hz) gives COLMAP pairs with many
    matches and almost no baseline; on a synthetic nuScenes-like drive its model then skewed the steps before
    the creep 20-30 deg off the heading, and the planar motion that replaced it (no body roll in its model) left
    the road unmeasurable: 12.7 % off the true path. Thinned, COLMAP kept its path to 0.25 %."""
    err, res = PavemapError("planar motion asked for"), None
    with held_records() as first_try:  # replayed unless the retry replaces the first try's model
        try:
            if method != "planar":
                res = _colmap_result(model(keyframes), names, keyframes, camera, camera_height, limits, hint, info)
        except PavemapError as e:
            err = e
    if res is None and method == "auto":
        retried = _coarser_colmap(model, str(err), images, names, keyframes, camera, camera_height, ego_mask,
                                  limits, hint, info)
        if retried is not None:
            retried[0].info["sfm_retry"]["first_try_warnings"] = warnings_of(first_try)
            return retried
    replay(first_try)
    if res is not None:
        return res, keyframes
    if method == "colmap":
        raise err
    if method == "auto":
        log.warning("SfM: %s; following the car's planar motion instead", err)
    info["sfm_failure"] = str(err)
    return planar_result(images, keyframes, camera, camera_height, ego_mask, limits.min_frames, info,
                         masks=masks), keyframes


def _colmap_result(rec, names: list[str], keyframes: np.ndarray, camera: Camera, camera_height: float,  # noqa: ANN001
                   limits: PartLimits, hint: str, info: dict) -> SfmResult:
    if rec is None:
        raise PavemapError(f"SfM failed: no reconstruction from {int(keyframes.sum())} keyframes ({hint})")
    res = metric_result(rec, names, keyframes, camera, camera_height, limits, hint, info)
    info["method"] = "pycolmap SfM"
    if info.get("translations_rejected"):
        raise PavemapError("SfM's steps point off the car's heading in most places (its translations are wrong)")
    return res


def _coarser_colmap(model: Callable[[np.ndarray], object], failure: str, images: list[Path], names: list[str],
                    keyframes: np.ndarray, camera: Camera, camera_height: float, ego_mask: np.ndarray | None,
                    limits: PartLimits, hint: str, info: dict) -> tuple[SfmResult, np.ndarray] | None:
    """COLMAP's second try on the keyframes that move ``RETRY_PARALLAX`` against the one before, or None (no
    fewer keyframes, too few, or it fails too: ``info["sfm_retry"]`` says so)."""
    kf = np.flatnonzero(keyframes)
    coarse = np.zeros_like(keyframes)
    coarse[kf[select_keyframes([images[i] for i in kf], RETRY_PARALLAX, ego_mask)]] = True
    if not limits.min_frames <= coarse.sum() < keyframes.sum():
        return None
    retry = {"first_try": failure, "keyframes_before": int(keyframes.sum()), "keyframes": int(coarse.sum()),
             "min_parallax": RETRY_PARALLAX}
    trial = {k: info[k] for k in _INPUT_KEYS if k in info}
    trial.update(keyframes=int(coarse.sum()), keyframe_index=np.flatnonzero(coarse).tolist(), sfm_retry=retry)
    with held_records() as said:
        try:
            res = _colmap_result(model(coarse), names, coarse, camera, camera_height, limits, hint, trial)
        except PavemapError as e:
            res, why = None, str(e)
    if res is None:
        info["sfm_retry"] = {**retry, "failed": why, "warnings": warnings_of(said)}
        return None
    replay(said)
    log.info("SfM: COLMAP failed on %d keyframes (%s); on %d with more parallax it did not", retry["keyframes_before"],
             failure, retry["keyframes"])
    info.clear()
    info.update(trial)
    res.info = info
    return res, coarse


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
    base = {k: v for k, v in res.info.items() if k in _INPUT_KEYS}
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
