"""Each turning step's yaw checked on the road: the planar motion's turn corrected where the road's image motion
fits a slightly different one clearly better.

The planar motion (:mod:`pavemap.sfm.planar`) finds a step's yaw from feature matches alone, with the car turning
about the mount's up axis. In a turn the car's body rolls a degree or two, and a feature-poor stretch leaves a
few dozen matches: on a synthetic 2 Hz turn of 15 deg steps it read some steps 3-5 deg short. The road's
homography depends on the turn too: the road warped from one view onto the next (:func:`pavemap.sfm.steps.sweep_step`)
matches best at the right yaw and step length. Here each step that turns is swept over yaw offsets of up to
``span_deg`` (the destination camera turned about the vertical, the chord by half as much, as on an arc), and
the offset whose road match peaks highest is taken where the road could not match the step at the planar motion's
own yaw (no trusted peak there): a yaw the road contradicts. Where it matches at the own yaw, a higher peak
elsewhere was as often noise (on a synthetic turn it moved a step read 0.2 deg off to 1.2 deg off).

Conventions: as :mod:`pavemap.sfm.steps` (poses camera-to-world, world z up).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pavemap.sfm.steps import StepConfig, StepEstimate, _Pair, _pairs, _pixel_rays, _road_roi, rot_z, sweep_step
from pavemap.types import Camera


@dataclass(frozen=True)
class YawConfig:
    """Yaw offsets searched per turning step: ``coarse_deg`` apart within ``span_deg``, then ``fine_deg`` either
    side of the best; only steps whose yaw is at least ``min_turn_deg`` (straight steps keep theirs)."""

    span_deg: float = 6.0
    coarse_deg: float = 2.0
    fine_deg: float = 1.0
    min_turn_deg: float = 2.0


def _turned(p: _Pair, rays: np.ndarray, h: float, d: float, cfg: StepConfig) -> StepEstimate:
    """The road's step sweep with the destination camera turned ``d`` rad about the vertical and the direction of
    travel by ``d / 2`` (the chord of an arc lies half-way between its headings)."""
    R_dst = rot_z(d) @ p.Tb[:3, :3]
    direction = rot_z(d / 2) @ p.direction
    up = np.array([0.0, 0.0, 1.0])
    normal = up - (up @ direction) * direction
    normal /= np.linalg.norm(normal)
    roi = _road_roi(rays, -R_dst.T @ normal, h, cfg, p.ego)
    if roi.sum() < 500:
        return StepEstimate(float("nan"), float("nan"), 0.0, False, np.zeros(0), np.zeros(0))
    return sweep_step(p.src, p.dst, p.K, p.Ta, R_dst, direction, normal, h, roi, p.ego, cfg)


def _best_offset(p: _Pair, rays: np.ndarray, h: float, cfg: StepConfig, ycfg: YawConfig) -> tuple[float, dict]:
    """(offset rad, record) of one step: 0 unless the road trusts no step length at the own yaw and one at a turned
    yaw (the best such)."""
    peaks: dict[float, float] = {}

    def peak(deg: float) -> float:
        if deg not in peaks:
            e = _turned(p, rays, h, np.radians(deg), cfg)
            peaks[deg] = e.peak if e.trusted and np.isfinite(e.peak) else -1.0
        return peaks[deg]

    coarse = np.arange(-ycfg.span_deg, ycfg.span_deg + 1e-9, ycfg.coarse_deg)
    best = max(coarse, key=peak)
    for deg in (best - ycfg.fine_deg, best + ycfg.fine_deg):
        if abs(deg) <= ycfg.span_deg:
            peak(deg)
    best = max(peaks, key=peaks.get)
    own = peak(0.0)
    # only a yaw the road contradicts: where it matches at the planar motion's own yaw, a slightly higher peak
    # elsewhere is as often the road's noise as a better turn (the planar yaw then stays)
    take = bool(best != 0.0 and peaks[best] > 0 and own < 0)
    record = {"step": p.i, "offset_deg": round(float(best), 2) if take else 0.0,
              "peak_own": round(own, 3), "peak_best": round(peaks[best], 3)}
    return (float(np.radians(best)) if take else 0.0), record


def road_yaw_offsets(images: list[Path], T_world_cam: np.ndarray, yaw: np.ndarray, camera: Camera,
                     camera_height: float, ego_mask: np.ndarray | None = None, cfg: YawConfig | None = None,
                     step_cfg: StepConfig | None = None) -> tuple[np.ndarray, list[dict]]:
    """(N-1,) yaw corrections (rad, left positive; 0 where the road did not clearly prefer another) of the steps
    of the path ``T_world_cam`` (N, 4, 4) whose yaw ``yaw`` (N-1,) rad turns at least ``min_turn_deg``, and a
    record per step searched (offset, the road's NCC peak at the own yaw and at the best)."""
    ycfg, scfg = cfg or YawConfig(), step_cfg or StepConfig()
    out = np.zeros(len(images) - 1)
    records: list[dict] = []
    turning = np.abs(np.degrees(np.nan_to_num(np.asarray(yaw, float)))) >= ycfg.min_turn_deg
    if not turning.any():
        return out, records
    rays = None
    for p in _pairs(images, T_world_cam, camera, camera_height, ego_mask, scfg):
        if not turning[p.i] or p.roi is None:
            continue
        rays = _pixel_rays(p.K, p.src.shape) if rays is None else rays
        out[p.i], rec = _best_offset(p, rays, camera_height, scfg, ycfg)
        records.append(rec)
    return out, records


__all__ = ["YawConfig", "road_yaw_offsets"]
