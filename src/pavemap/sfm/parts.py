"""Keep what can be kept: a car's path cut where SfM broke it, and the longest consistent part kept.

A real clip has stretches SfM cannot register (a grey wall, a bus filling the view) and stretches where a
frame was registered wrongly (the path jumps or slides sideways). Refusing the whole clip throws away
the good part; keeping everything writes a path that teleports. So the keyframes' path, still in SfM's
units, is cut at each unregistered keyframe and at each step a car cannot make, and the longest part
is kept; every other frame is named with the reason it was dropped.

A car's step, checked without a metric scale (the scale comes later, from the road):

- **no rotation jump**: the heading changes by at most ``max_turn_deg`` between two keyframes (a car in a
  tight turn at 2 Hz: ~15 deg); a frame registered with a wrong rotation breaks the path there;
- **no teleport**: a step longer than ``max_step_ratio`` x the median of the moving steps around it breaks
  the path (a stop is fine: short steps are never cut);
- **no skid** (non-holonomic motion): a car moves along its heading. A moving step whose direction lies more
  than ``max_skid_deg`` off the camera's heading (the mean of the two frames' forward axes on the road plane,
  the chord of a turn), once the mount's own yaw is taken out, is not cut but *repaired*: forward-motion SfM
  gets rotations right long before translations (on a 2 Hz clip into a car park it put the camera moving
  backwards while turning right), so the step takes the heading's direction and the road's image motion
  measures its length afterwards (:mod:`pavemap.sfm.steps`).

Conventions: ``C`` (R, 3) camera centres and ``fwd`` (R, 3) the cameras' forward (z) axes, SfM world,
``up`` (3,) unit; ``R`` = the keyframes registered, in video order.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class PartLimits:
    """When a step of the path breaks it, or is repaired (see the module doc)."""

    max_turn_deg: float = 35.0
    max_step_ratio: float = 4.0
    max_skid_deg: float = 15.0
    window: int = 3  # steps either side for the local median step length
    min_frames: int = 5  # a part shorter than this is nothing to map


def _flat(a: np.ndarray, up: np.ndarray) -> np.ndarray:
    return a - np.outer(a @ up, up)


def _unit(a: np.ndarray) -> np.ndarray:
    return a / np.maximum(np.linalg.norm(a, axis=-1, keepdims=True), 1e-12)


def heading_chords(fwd: np.ndarray, up: np.ndarray) -> np.ndarray:
    """(R-1, 3) unit direction of each step by the car's heading: the mean of the two frames' forward axes
    ``fwd`` (R, 3) on the road plane (the chord of a circular turn)."""
    f = _unit(_flat(fwd, up))
    return _unit(f[:-1] + f[1:])


def step_flags(C: np.ndarray, fwd: np.ndarray, up: np.ndarray, limits: PartLimits) -> dict:
    """Per step i -> i+1 of the path (R-1,): ``breaks`` (bool) and ``why`` (a sentence, "" when fine),
    ``skids`` (bool: moving and off the heading, to repair), ``reverse`` (most steps go backwards along the
    heading) and the figures ``turn_deg``, ``step_ratio``, ``skid_deg`` (None where not judged) and
    ``mount_yaw_deg``."""
    d = np.diff(C, axis=0)
    n = len(d)
    L = np.linalg.norm(d, axis=1)
    out = {"breaks": np.zeros(n, dtype=bool), "why": [""] * n, "skids": np.zeros(n, dtype=bool),
           "turn_deg": [None] * n, "step_ratio": [None] * n, "skid_deg": [None] * n, "mount_yaw_deg": 0.0,
           "reverse": False}
    if n == 0:
        return out
    f = _unit(_flat(fwd, up))
    turn = np.degrees(np.arccos(np.clip((f[1:] * f[:-1]).sum(1), -1.0, 1.0)))
    med = float(np.median(L))
    moving = 0.25 * med < L if med > 0 else L > 0
    chord = heading_chords(fwd, up)
    dir_flat = _unit(_flat(d, up))
    ang = np.degrees(np.arctan2((dir_flat * np.cross(up, chord)).sum(1), (dir_flat * chord).sum(1)))
    # a car moves along its heading, forwards or in reverse: most moving steps pointing backwards is a clip
    # driven (or, far more often, numbered) in reverse, and the heading's other end is the reference
    reverse = bool(moving.any() and np.median(np.cos(np.radians(ang[moving]))) < 0)
    if reverse:
        ang = (ang + 360.0) % 360.0 - 180.0
    out["reverse"] = reverse
    # the mount's yaw to the car's axis: the median over moving steps, if it is a dashcam's (a few degrees);
    # a larger median means most steps are wrong, not that the camera looks sideways
    yaw = float(np.median(ang[moving])) if moving.any() else 0.0
    yaw = yaw if abs(yaw) <= limits.max_skid_deg else 0.0
    out["mount_yaw_deg"] = round(yaw, 2)
    for i in range(n):
        out["turn_deg"][i] = round(float(turn[i]), 1)
        if turn[i] > limits.max_turn_deg:
            out["breaks"][i] = True
            out["why"][i] = f"the heading jumps {turn[i]:.0f} deg in one step (limit {limits.max_turn_deg:g} deg)"
        if not moving[i]:
            continue
        s = float(((ang[i] - yaw) + 180.0) % 360.0 - 180.0)
        out["skid_deg"][i] = round(s, 1)
        out["skids"][i] = abs(s) > limits.max_skid_deg
        lo, hi = max(0, i - limits.window), min(n, i + limits.window + 1)
        near = [j for j in range(lo, hi) if j != i and moving[j]]
        if near and not out["skids"][i] and not out["breaks"][i]:
            r = float(L[i] / np.median(L[near]))
            out["step_ratio"][i] = round(r, 2)
            if r > limits.max_step_ratio:
                out["breaks"][i] = True
                out["why"][i] = f"the path jumps: step {r:.1f}x the steps around it (limit {limits.max_step_ratio:g}x)"
    return out


def repair_skids(C: np.ndarray, fwd: np.ndarray, up: np.ndarray, skids: np.ndarray, mount_yaw_deg: float = 0.0,
                 reverse: bool = False) -> np.ndarray:
    """Positions (R, 3) with each skidding step (``skids`` (R-1,) bool) turned onto the heading's chord (plus the
    mount's yaw; backwards along it for a ``reverse`` clip), level with the road, at the median length of the
    sound moving steps (the road's image motion measures it afterwards). The other steps are kept as SfM made
    them."""
    d = np.diff(C, axis=0)
    if not skids.any():
        return C.copy()
    L = np.linalg.norm(d, axis=1)
    sound = ~skids & (L > 0)
    length = float(np.median(L[sound])) if sound.any() else float(np.median(L[L > 0])) if (L > 0).any() else 1.0
    chord = heading_chords(fwd, up)
    a = np.radians(mount_yaw_deg)
    along = (-1.0 if reverse else 1.0) * (np.cos(a) * chord + np.sin(a) * np.cross(up, chord))
    # a skid's length is as suspect as its direction (keeping SfM's lengths made a restart after a stop jump
    # by 1.6 g on a synthetic drive): the median, for the road to measure
    d[skids] = length * along[skids]
    return np.vstack([C[:1], C[:1] + np.cumsum(d, axis=0)])


def consistent_parts(registered: np.ndarray, C: np.ndarray, fwd: np.ndarray, up: np.ndarray,
                     limits: PartLimits | None = None) -> tuple[np.ndarray, dict[int, str], dict]:
    """The longest consistent part of a path over keyframes.

    ``registered`` (K,) bool over the keyframes in video order; ``C`` / ``fwd`` (K, 3) (rows of unregistered
    keyframes ignored). Returns ``keep`` (K,) bool (the kept part), ``dropped`` {keyframe position: reason}
    for every other keyframe, and the figures: ``parts`` [[first, last, kept], ...] (keyframe positions),
    ``flags`` (:func:`step_flags` of the registered keyframes' path, steps between registered neighbours).
    """
    limits = limits or PartLimits()
    K = len(registered)
    reg = np.flatnonzero(registered)
    keep = np.zeros(K, dtype=bool)
    dropped: dict[int, str] = {int(i): "not registered by SfM" for i in np.flatnonzero(~registered)}
    if reg.size == 0:
        return keep, dropped, {"parts": [], "flags": step_flags(C[:0], fwd[:0], up, limits)}
    flags = step_flags(C[reg], fwd[reg], up, limits)
    bad, why = flags["breaks"], flags["why"]
    # a part ends at an unregistered keyframe (a gap in ``reg``) or at a step that breaks the path
    cut_after = [(k, why[k]) for k in range(len(reg) - 1) if bad[k]]
    cut_after += [(k, "") for k in range(len(reg) - 1) if reg[k + 1] != reg[k] + 1 and not bad[k]]
    cuts = sorted(cut_after)
    bounds = [-1] + [k for k, _ in cuts] + [len(reg) - 1]
    parts = [(bounds[j] + 1, bounds[j + 1]) for j in range(len(bounds) - 1)]
    lengths = [float(np.linalg.norm(np.diff(C[reg[a:b + 1]], axis=0), axis=1).sum()) for a, b in parts]
    best = max(range(len(parts)), key=lambda j: (parts[j][1] - parts[j][0], lengths[j]))
    a, b = parts[best]
    keep[reg[a:b + 1]] = True
    reason_at = dict(cuts)
    for j, (p0, p1) in enumerate(parts):
        if j == best:
            continue
        # the break between the kept part and this side of it
        cause = reason_at.get(b if j > best else a - 1, "")
        span = f"frames of keyframes {int(reg[p0])}-{int(reg[p1])}"
        text = cause or "separated from the kept part by frames SfM could not register"
        for i in reg[p0:p1 + 1]:
            dropped[int(i)] = f"in a shorter part ({span}): {text}"
    parts_out = [[int(reg[p0]), int(reg[p1]), j == best] for j, (p0, p1) in enumerate(parts)]
    return keep, dropped, {"parts": parts_out, "flags": flags}


__all__ = ["PartLimits", "consistent_parts", "heading_chords", "repair_skids", "step_flags"]
