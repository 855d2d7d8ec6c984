"""The ego vehicle in its own camera: image regions that stay the same across a clip.

A car camera sees parts of its own car (bonnet, dashboard, a mount, a logo) at the same pixels in
every frame. Features there move *with* the camera, so SfM reads them as points at infinity or as
zero motion, and the texture / detection stages would paint the bonnet onto the road. This module
finds that region automatically (:func:`detect_ego_mask`) or reads it from a mask image
(:func:`read_ego_mask`), and writes it to the sequence (``masks/<camera>.png``, 255 = ego).

Detection: frames spread over the clip are reduced to a small grey image; a pixel is *static*
when its temporal standard deviation is small both absolutely and relative to the image's typical
variation (the scene moves past everywhere else). Only static regions connected to the bottom or
side borders count (the ego vehicle enters the picture from an edge; uniform sky connected to the
top does not count), and the region is taken as a per-column profile from the bottom up, cleaned
morphologically, then scaled back to full resolution.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image

from pavemap.errors import PavemapError

#: Where a sequence keeps the ego masks, relative to its folder.
MASKS_DIR = "masks"


@dataclass
class EgoMaskReport:
    """What was masked: ``pixels`` ego pixels of ``width`` × ``height``; ``rows`` the image rows it spans."""

    pixels: int
    width: int
    height: int
    rows: tuple[int, int] | None  # (first, last) row holding ego pixels; None when empty
    source: str  # "auto", a file path, or "none"

    @property
    def fraction(self) -> float:
        return self.pixels / max(1, self.width * self.height)

    def describe(self) -> str:
        if self.pixels == 0:
            return f"ego mask ({self.source}): none found"
        where = "bottom" if self.rows and self.rows[1] >= self.height - 2 else "inside"
        return (f"ego mask ({self.source}): {self.pixels} px ({self.fraction:.1%}) at the {where} of the image, "
                f"rows {self.rows[0]}-{self.rows[1]}" if self.rows else "")

    def to_dict(self) -> dict:
        return {"pixels": self.pixels, "fraction": round(self.fraction, 4), "rows": list(self.rows or ()),
                "source": self.source}


def _grey_small(path: Path, width: int) -> np.ndarray:
    """(h, width) float32 grey image in [0, 255], box-filtered down."""
    with Image.open(path) as im:
        w, h = im.size
        g = im.convert("L").resize((width, max(8, round(h * width / w))), Image.Resampling.BOX)
        return np.asarray(g, dtype=np.float32)


def _ncc(a: np.ndarray, b: np.ndarray, r: int) -> tuple[np.ndarray, np.ndarray]:
    """Local normalised cross-correlation of two (h, w) images in (2r+1)² windows, and the smaller local variance."""
    from scipy import ndimage

    def f(x: np.ndarray) -> np.ndarray:
        return ndimage.uniform_filter(x, 2 * r + 1)

    ma, mb = f(a), f(b)
    va, vb = f(a * a) - ma * ma, f(b * b) - mb * mb
    return (f(a * b) - ma * mb) / np.sqrt(np.maximum(va * vb, 1e-6)), np.minimum(va, vb)


def static_score(images: list[Path], max_frames: int = 20, work_width: int = 320, gap: int = 3,
                 radius: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """(h, w) median local NCC between frames ``gap`` samples apart, and (h, w) median local variance.

    The scene moves past the camera, so its patches decorrelate; the ego vehicle's patches keep their
    pattern up to brightness and contrast (exposure, reflections), hence NCC rather than intensity
    variance (a white bonnet's grey level swings with what it reflects).
    """
    from scipy import ndimage

    pick = np.unique(np.linspace(0, len(images) - 1, min(max_frames, len(images))).round().astype(int))
    s = [ndimage.gaussian_filter(_grey_small(Path(images[i]), work_width), 0.7) for i in pick]
    pairs = [(i, j) for i in range(len(s)) for j in range(i + gap, len(s), gap)] or [(0, len(s) - 1)]
    ncc, var = zip(*(_ncc(s[i], s[j], radius) for i, j in pairs), strict=True)
    return np.median(np.stack(ncc), 0), np.median(np.stack(var), 0)


def detect_ego_mask(images: list[Path], width: int, height: int, max_frames: int = 20, work_width: int = 320,
                    min_ncc: float = 0.5, weak_ncc: float = 0.25, flat_var: float = 1.5, min_below: float = 0.6,
                    max_gap: int = 5, margin: int = 2, min_cols: float = 0.2,
                    min_static_share: float = 0.67) -> np.ndarray:
    """(height, width) bool mask, True on the ego vehicle, from ``images`` of one camera (video order).

    A pixel is *static* when textured (local variance > ``flat_var``) and its median NCC across
    frames is > ``min_ncc``; a *candidate* when flat or its NCC is > ``weak_ncc``. Per column the
    ego region reaches up to the highest static pixel in the lower half with at least ``min_below``
    of the pixels below it candidates and no ``max_gap`` moving rows in a row below it (flat road
    above the bonnet's edge is not included). Fewer than ``min_cols`` of the columns with ego pixels
    means no ego vehicle; the profile is cleaned over columns and ``margin`` rows (work resolution)
    are added on top. A region whose textured pixels are less than ``min_static_share`` static is no
    ego vehicle either: a car's own parts are rigid and fixed to the camera, while a region pieced
    together from road that merely looks alike over a short straight clip (a solid lane line moving
    along itself, the car's own shadow, smooth asphalt) is half moving. Needs ≥ 6 frames.
    """
    from scipy import ndimage

    if len(images) < 6:
        return np.zeros((height, width), dtype=bool)
    ncc, var = static_score(images, max_frames, work_width)
    textured = var > flat_var
    static = textured & (ncc > min_ncc)
    # the run from the bottom may cross weakly correlated pixels (a bonnet's reflections change), not moving road
    cand = (ncc > weak_ncc) | ~textured
    h, w = static.shape
    # per column, rows counted from the bottom: the ego region reaches the highest static pixel in the
    # lower half below which most pixels are candidates (a bonnet's lower part may reflect the moving
    # scene, so it need not be static everywhere; the moving road below a static-looking spot is not)
    c_up, s_up = cand[::-1], static[::-1]
    frac = np.cumsum(c_up, 0) / np.arange(1, h + 1)[:, None]
    # and no long gap of moving pixels below it: the ego region is connected to the bottom
    gap = ndimage.uniform_filter1d((~c_up).astype(float), size=max_gap, axis=0, origin=-(max_gap // 2)) >= 0.999
    below_gap = np.cumsum(gap, 0) > 0
    ok = s_up & (frac >= min_below) & ~below_gap & (np.arange(h) < h // 2)[:, None]
    # a bonnet's edge runs across the image, near-horizontal: most columns around hold an anchor within a
    # few rows. Lane lines on a straight road are static too, but diagonal: their anchors lack that support
    band = ndimage.maximum_filter1d(ok.astype(np.uint8), size=2 * max(2, h // 30) + 1, axis=0)
    support = ndimage.uniform_filter1d(band.astype(float), size=max(3, w // 4) | 1, axis=1, mode="constant")
    ok &= support >= 0.5
    top = np.where(ok.any(0), h - 1 - np.argmax(ok[::-1], 0), -1)
    run = np.where(ok.sum(0) >= 2, top + 1, 0)
    if (run > 0).mean() < min_cols:
        return np.zeros((height, width), dtype=bool)
    # a column that missed its anchors (glare, a flat patch) takes its neighbours' height: inner holes are
    # interpolated, then a wide median (a tenth of the width) keeps the smooth outline of a bonnet
    valid = np.flatnonzero(run > 0)
    inner = (np.arange(w) > valid[0]) & (np.arange(w) < valid[-1]) & (run == 0)
    run[inner] = np.round(np.interp(np.flatnonzero(inner), valid, run[valid])).astype(int)
    run = ndimage.median_filter(run, size=max(3, w // 10) | 1, mode="nearest")
    run = ndimage.grey_closing(run, size=max(3, w // 10) | 1, mode="nearest")  # fills notches (a reflected line)
    run = np.where(run > 0, run + margin, 0)  # keycorners right on the edge see the bonnet too
    small = np.arange(h)[:, None] >= (h - run)[None, :]
    if not rigid(small, ncc, var, min_ncc, flat_var, min_static_share):
        return np.zeros((height, width), dtype=bool)
    full = np.asarray(Image.fromarray(small.astype(np.uint8) * 255).resize((width, height), Image.Resampling.NEAREST))
    return full > 127


def rigid(region: np.ndarray, ncc: np.ndarray, var: np.ndarray, min_ncc: float = 0.5, flat_var: float = 1.5,
          min_share: float = 0.67) -> bool:
    """Whether ``region`` (h, w) bool is static like a part of the car: at least ``min_share`` of its textured
    pixels (local variance ``var`` > ``flat_var``) have a median NCC ``ncc`` (h, w) above ``min_ncc``.

    Measured (`detect_ego_mask`'s regions): the real nuScenes bonnets 0.79 and 0.93, a drawn bonnet 0.90;
    false regions on short synthetic straight drives (lane line, the car's shadow, smooth asphalt) 0.43-0.57."""
    tex = region & (var > flat_var)
    return bool(tex.any() and (ncc[tex] > min_ncc).mean() >= min_share)


def read_ego_mask(path: str | os.PathLike, width: int, height: int) -> np.ndarray:
    """A user's mask image → (height, width) bool, True on the ego vehicle (white / non-zero = ego)."""
    p = Path(path)
    try:
        with Image.open(p) as im:
            if im.size != (width, height):
                raise PavemapError(f"{p}: ego mask is {im.size[0]}x{im.size[1]}, the images are {width}x{height}")
            a = np.asarray(im.convert("L"))
    except FileNotFoundError:
        raise PavemapError(f"{p}: ego mask not found") from None
    except OSError as e:
        raise PavemapError(f"{p}: unreadable ego mask ({e})") from None
    return a > 127


def mask_report(mask: np.ndarray, source: str) -> EgoMaskReport:
    rows = np.flatnonzero(mask.any(1))
    return EgoMaskReport(int(mask.sum()), mask.shape[1], mask.shape[0],
                         (int(rows[0]), int(rows[-1])) if rows.size else None, source)


def write_ego_mask(mask: np.ndarray, seq_root: str | os.PathLike, camera: str) -> str:
    """Write ``masks/<camera>.png`` (255 = ego) under the sequence folder; returns the relative path."""
    from pavemap.io.atomic import atomic_path

    rel = f"{MASKS_DIR}/{camera}.png"
    dst = Path(seq_root) / rel
    dst.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(dst) as tmp:
        Image.fromarray(mask.astype(np.uint8) * 255).save(tmp, format="PNG")
    return rel


def store_ego_masks(cameras: dict, masks: dict[str, np.ndarray | None], seq_root: str | os.PathLike) -> None:
    """Write each camera's non-empty mask to ``masks/<camera>.png`` and point ``Camera.ego_mask`` at it."""
    for name, m in masks.items():
        if m is not None and m.any():
            cameras[name].ego_mask = write_ego_mask(m, seq_root, name)


def load_ego_mask(seq_root: str | os.PathLike | None, rel: str | None, width: int, height: int) -> np.ndarray | None:
    """The stored ego mask of a camera, (height, width) bool, or None when the camera has none."""
    if rel is None or seq_root is None:
        return None
    return read_ego_mask(Path(seq_root) / rel, width, height)


def ego_mask_at(seq: object, camera: str, width: int, height: int) -> np.ndarray | None:
    """The camera's stored ego mask resampled to ``width`` x ``height`` (nearest), (height, width) bool; None
    when the camera has none. What stage 1 and the ground points leave out (``seq`` a Sequence)."""
    cam = seq.cameras[camera]  # type: ignore[attr-defined]
    full = load_ego_mask(getattr(seq, "root", None), cam.ego_mask, cam.width, cam.height)
    if full is None or not full.any():
        return None
    if full.shape == (height, width):
        return full
    ys = np.minimum((np.arange(height) + 0.5) * full.shape[0] / height, full.shape[0] - 1).astype(np.int64)
    xs = np.minimum((np.arange(width) + 0.5) * full.shape[1] / width, full.shape[1] - 1).astype(np.int64)
    return full[ys[:, None], xs[None, :]]


def resolve_ego_mask(spec: str | os.PathLike | None, images: list[Path], width: int, height: int,
                     default_auto: bool) -> tuple[np.ndarray | None, EgoMaskReport]:
    """The ego mask an import asks for: ``spec`` "auto", "none", a mask image, or None (= ``default_auto``).

    Returns (mask (height, width) bool or None when empty / not asked, the report) and logs the report.
    """
    import logging

    s = "auto" if spec is None and default_auto else ("none" if spec is None else str(spec))
    if s.lower() == "none":
        mask, source = np.zeros((height, width), dtype=bool), "none"
    elif s.lower() == "auto":
        mask, source = detect_ego_mask(images, width, height), "auto"
    else:
        mask, source = read_ego_mask(s, width, height), s
    rep = mask_report(mask, source)
    logging.getLogger(__name__).info("%s", rep.describe())
    return (mask if mask.any() else None), rep


def colmap_mask(mask: np.ndarray, path: str | os.PathLike) -> Path:
    """Write ``mask`` for COLMAP's ``camera_mask_path`` (COLMAP ignores features where the mask is 0)."""
    p = Path(path)
    Image.fromarray(np.where(mask, 0, 255).astype(np.uint8)).save(p, format="PNG")
    return p


__all__ = ["MASKS_DIR", "EgoMaskReport", "colmap_mask", "detect_ego_mask", "load_ego_mask", "mask_report",
           "read_ego_mask", "resolve_ego_mask",
           "store_ego_masks", "write_ego_mask"]
