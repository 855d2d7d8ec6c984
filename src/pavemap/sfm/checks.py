"""Keyframes by parallax and sanity checks of an SfM result (:mod:`pavemap.sfm.pipeline`).

A broken reconstruction (a static bonnet read as scene, a bus taken for the street, too little
motion) must stop the import with one clear line rather than write a sequence whose poses jump.
:func:`check_sfm` measures what a car's trajectory must satisfy and raises
:class:`~pavemap.errors.PavemapError` naming the first failed check.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pavemap.errors import PavemapError

log = logging.getLogger(__name__)


@dataclass
class SfmChecks:
    """Limits of :func:`check_sfm` (the figures it reports sit in ``SfmResult.info``).

    - ``min_registered``: share of the keyframes that must be kept (0: any; the longest consistent part
      decides, :class:`pavemap.sfm.parts.PartLimits`, and the frames left out are named).
    - ``max_reproj_px``: mean reprojection error of the model.
    - ``max_turn_deg``: largest heading change between consecutive steps of the path.
    - ``max_step_ratio``: largest ratio of consecutive step lengths (a car does not teleport); steps
      under a quarter of the median (stop and go) are left out, and two steps that both took the road's own
      length are reported (``step_ratio_unchecked``), not refused.
    - ``max_accel_mps2``: largest change of the path's speed per second, where the frame times are known
      (a video's frame rate, ``--fps``): speeds are averaged over ``accel_window_s`` so that the SfM
      positions' noise (~0.1 m) stays ~0.6 m/s² of it at 2 Hz. No car brakes or accelerates by more than ~1 g;
      the same limit holds at a wrong scale of ±50 %, which the camera height fixes anyway.
    - ``nominal_times``: the frame times are a claim, not a measurement (``--fps`` of an image folder: keyframes
      exported from a log are often irregular, nuScenes' 2 Hz ones by ±10 %): a speed change past the limit is
      reported and warned about, not refused; a video's timestamps are measured and are enforced.
    - ``max_height_dev``: largest deviation of the 10th / 90th percentile of the per-camera heights over
      the road from their median, as a share of it (the mount does not move: a wandering height means
      a wrong geometry). Per-camera heights from local road planes are noisy on smooth real asphalt
      (±15 % on the nuScenes clip), so this catches gross failures only. Not measured at all (no road found
      under the path) is reported as unchecked, not refused.
    - ``min_median_step_m``: the keyframes were chosen because the image moved, so the path between them
      must move too: a median step under this (metres) means a static part of the view (a bonnet, a
      dashboard) was read as the scene.
    """

    min_registered: float = 0.0
    max_reproj_px: float = 2.0
    max_turn_deg: float = 30.0
    max_step_ratio: float = 10.0
    max_accel_mps2: float = 10.0
    accel_window_s: float = 1.0
    max_height_dev: float = 0.2
    min_median_step_m: float = 0.05
    nominal_times: bool = False


def select_keyframes(images: list[Path], min_parallax: float = 0.01, mask: np.ndarray | None = None,
                     work_width: int = 480) -> np.ndarray:
    """(N,) bool: frames kept as SfM keyframes, in video order.

    A frame is kept when the median optical flow of tracked corners since the last keyframe is at
    least ``min_parallax`` × the image width (a stopped car's frames add nothing but degenerate
    pairs). The first and last frames are always kept. ``mask`` (H, W) True = ignore (ego vehicle).
    """
    import cv2

    n = len(images)
    keep = np.zeros(n, dtype=bool)
    if n == 0:
        return keep
    keep[0] = True

    from pavemap.io.sequence import load_gray

    def load(p: Path) -> np.ndarray:
        return load_gray(p, work_width)

    last = load(images[0])
    m8 = None
    if mask is not None:
        m8 = cv2.resize((~mask).astype(np.uint8) * 255, (last.shape[1], last.shape[0]), interpolation=cv2.INTER_NEAREST)
    for i in range(1, n):
        cur = load(images[i])
        pts = cv2.goodFeaturesToTrack(last, 400, 0.01, 7, mask=m8)
        if pts is None or len(pts) < 10:
            keep[i], last = True, cur  # too little texture to judge: keep it and let SfM decide
            continue
        nxt, st, _ = cv2.calcOpticalFlowPyrLK(last, cur, pts, None)
        ok = st.reshape(-1) == 1
        flow = np.linalg.norm((nxt - pts).reshape(-1, 2)[ok], axis=1) if ok.any() else np.array([np.inf])
        if float(np.median(flow)) >= min_parallax * work_width:
            keep[i], last = True, cur
    keep[-1] = True
    return keep


def path_acceleration(C: np.ndarray, times: np.ndarray, window_s: float) -> tuple[float, float] | None:
    """Largest |change of speed| per second along the path ``C`` (R, 3) m at ``times`` (R,) s, and the time
    (s) where it starts: speeds are path length over ``window_s``, compared one window apart. None when the
    path spans less than two windows or the times do not increase."""
    t = np.asarray(times, dtype=np.float64)
    if len(t) < 3 or not np.all(np.diff(t) > 0) or t[-1] - t[0] < 2 * window_s:
        return None
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(C, axis=0), axis=1))])

    def speed(a: np.ndarray) -> np.ndarray:
        return (np.interp(a + window_s, t, s) - np.interp(a, t, s)) / window_s

    start = t[t + 2 * window_s <= t[-1] + 1e-9]
    acc = np.abs(speed(start + window_s) - speed(start)) / window_s
    k = int(np.argmax(acc))
    return float(acc[k]), float(start[k])


def check_sfm(info: dict, C: np.ndarray, heights: np.ndarray, checks: SfmChecks, hint: str = "",
              times: np.ndarray | None = None) -> dict:
    """Measure the trajectory ``C`` (R, 3, metric) and per-camera ``heights`` (R,) m; raise on a failed check.
    ``times`` (R,) s of the cameras, when known (a video's frame rate): the speed changes are checked too.

    Returns the figures (also on success): ``registered_share``, ``reproj_px``, ``max_turn_deg``,
    ``max_step_ratio``, ``max_accel_mps2`` (None without times), ``height_dev`` (10th/90th percentile vs
    median), ``height_range_m``, ``height_p10_p90_m``, ``heights_measured``, ``heights_m`` (per camera).
    """
    steps = np.diff(C, axis=0)
    L = np.linalg.norm(steps, axis=1)
    # a stopped car makes short steps, and restarts: only steps of a moving car are compared
    moving = 0.25 * float(np.median(L)) < L if L.size else L > 0
    turn = 0.0
    ratio = ratio_sfm = 1.0
    if moving.sum() >= 2:
        s = steps[moving] / L[moving, None]
        cos = np.clip((s[1:] * s[:-1]).sum(1), -1.0, 1.0)
        turn = float(np.degrees(np.arccos(cos)).max())
        r = L[moving][1:] / L[moving][:-1]
        r = np.maximum(r, 1.0 / r)
        ratio = float(r.max())
        # the jump guards against a scale jump of the SfM; two steps that both took the road's own length are
        # what the road measured (a missing frame, hard braking), and are reported, not refused
        own = np.asarray((info.get("road_steps") or {}).get("own_reading") or [], bool)
        road = own[moving][1:] & own[moving][:-1] if len(own) == len(L) else np.zeros(len(r), bool)
        ratio_sfm = float(r[~road].max()) if (~road).any() else 1.0
    h = heights[np.isfinite(heights)]
    med = float(np.median(h)) if h.size else float("nan")
    # one camera's local road plane is noisy (few points, a kerb): judge the 10th-90th percentile band,
    # which a wrong geometry (a drifting height) widens and a few noisy cameras do not
    p10, p90 = (float(np.percentile(h, q)) for q in (10, 90)) if h.size else (float("nan"),) * 2
    dev = max(p90 - med, med - p10) / med if h.size else float("inf")
    acc = path_acceleration(C, times, checks.accel_window_s) if times is not None else None
    figures = {
        "registered_share": round(info["registered"] / max(1, info["keyframes"]), 3),
        "reproj_px": round(float(info["reproj_px"]), 3),
        "max_turn_deg": round(turn, 2),
        "max_step_ratio": round(ratio, 2),
        "max_accel_mps2": None if acc is None else round(acc[0], 2),
        "frame_times": None if times is None else ("nominal" if checks.nominal_times else "measured"),
        "height_dev": round(dev, 4),
        "height_range_m": [round(float(h.min()), 3), round(float(h.max()), 3)] if h.size else None,
        "height_p10_p90_m": [round(p10, 3), round(p90, 3)] if h.size else None,
        "heights_measured": int(h.size),
        # each registered camera's height over the road under it, in path order (None: no road measured there)
        "heights_m": [round(float(x), 3) if np.isfinite(x) else None for x in heights],
    }
    tail = f"; {hint}" if hint else ""
    if L.size and float(np.median(L)) < checks.min_median_step_m:
        raise PavemapError(f"SfM sanity check failed: the path hardly moves ({float(L.sum()):.2f} m over {len(C)} "
                           f"frames whose images move): a static part of the view was read as the scene{tail}")
    if figures["registered_share"] < checks.min_registered:
        raise PavemapError(f"SfM registered only {info['registered']} of {info['keyframes']} keyframes "
                           f"(need {checks.min_registered:.0%}){tail}")
    if figures["reproj_px"] > checks.max_reproj_px:
        raise PavemapError(f"SfM sanity check failed: mean reprojection error {figures['reproj_px']:.2f} px "
                           f"> {checks.max_reproj_px} px{tail}")
    if turn > checks.max_turn_deg:
        raise PavemapError(f"SfM sanity check failed: the path turns {turn:.0f}° between two steps "
                           f"(> {checks.max_turn_deg:.0f}°): the trajectory is not a car's{tail}")
    if ratio_sfm > checks.max_step_ratio:
        raise PavemapError(f"SfM sanity check failed: one step of the path is {ratio_sfm:.1f}× the previous one "
                           f"(> {checks.max_step_ratio}): the trajectory jumps{tail}")
    if ratio > checks.max_step_ratio:
        figures["step_ratio_unchecked"] = (f"one step of the path is {ratio:.1f}× the one before or after it "
                                           f"(> {checks.max_step_ratio:g}), both as the road measured them: a "
                                           "frame missing from the clip, or hard braking; not refused")
        log.warning("SfM: %s", figures["step_ratio_unchecked"])
    if acc is not None and acc[0] > checks.max_accel_mps2 and checks.nominal_times:
        figures["accel_unchecked"] = (f"the path's speed changes by {acc[0]:.1f} m/s within one second "
                                      f"{acc[1]:.1f}-{acc[1] + 2 * checks.accel_window_s:.1f} s into the drive "
                                      f"(> {checks.max_accel_mps2:g} m/s²) at the nominal frame times: irregular "
                                      "frame times or a mis-measured step; not refused")
        log.warning("SfM: %s", figures["accel_unchecked"])
    elif acc is not None and acc[0] > checks.max_accel_mps2:
        raise PavemapError(f"SfM sanity check failed: the path's speed changes by {acc[0]:.1f} m/s within one "
                           f"second {acc[1]:.1f}-{acc[1] + 2 * checks.accel_window_s:.1f} s into the drive "
                           f"(> {checks.max_accel_mps2:g} m/s², about 1 g): the trajectory is not a car's; "
                           f"frames are mis-registered{tail}")
    if h.size < max(3, len(C) // 3):
        # not measured is not wrong: the path stands on its other checks, and says the height went unchecked
        figures["height_unchecked"] = (f"the road under the path was found below only {h.size} of {len(C)} "
                                       "cameras: the camera height along the path is not checked")
        log.warning("SfM: %s", figures["height_unchecked"])
    elif dev > checks.max_height_dev:
        raise PavemapError(f"SfM sanity check failed: the camera height over the road varies by {dev:.0%} along "
                           f"the path (limit {checks.max_height_dev:.0%}): the geometry is wrong{tail}")
    return figures


__all__ = ["SfmChecks", "check_sfm", "path_acceleration", "select_keyframes"]
