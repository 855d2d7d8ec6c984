"""Pixels of a sequence's views as flat tensors (the training / evaluation pool of stage 1)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from PIL import Image

from pavemap.io.egomask import ego_mask_at
from pavemap.io.sequence import load_depth, load_rgb, load_semantics
from pavemap.types import Sequence, View


@dataclass
class ViewKey:
    frame: int
    camera: str


@dataclass
class PixelPool:
    """Usable pixels of a set of views at one image scale.

    keys: the views; K (V, 3, 3) float32 intrinsics at that scale; T (V, 4, 4) float32
    camera-to-world. Per pixel (P,): view long, uv (P, 2) float32 pixel centres (a depth pixel: its
    LiDAR return's exact position, see _depth_samples), rgb (P, 3) uint8,
    channel long (semantic channel, -1 unknown), road bool (ground-truth road class), depth (P,)
    float32 metres (0 unknown, and 0 where the pixel's class is not ground: ``SemanticClass.ground``) or
    None. Only pixels kept by the loss mask (not movable, not sky) are stored.
    """

    keys: list[ViewKey]
    K: torch.Tensor
    T: torch.Tensor
    view: torch.Tensor
    uv: torch.Tensor
    rgb: torch.Tensor
    channel: torch.Tensor
    road: torch.Tensor
    depth: torch.Tensor | None

    def __len__(self) -> int:
        return int(self.view.numel())

    def to(self, device: torch.device) -> PixelPool:
        f = lambda t: None if t is None else t.to(device)  # noqa: E731
        return PixelPool(self.keys, f(self.K), f(self.T), f(self.view), f(self.uv), f(self.rgb),
                         f(self.channel), f(self.road), f(self.depth))

    def subset(self, keep: torch.Tensor) -> PixelPool:
        d = None if self.depth is None else self.depth[keep]
        return PixelPool(self.keys, self.K, self.T, self.view[keep], self.uv[keep], self.rgb[keep],
                         self.channel[keep], self.road[keep], d)


def _resize(a: np.ndarray, size: tuple[int, int], nearest: bool) -> np.ndarray:
    if a.shape[1] == size[0] and a.shape[0] == size[1]:
        return a
    if nearest:
        # Pick the source pixel under each target pixel centre (keeps labels and sparse depth exact).
        h, w = a.shape[:2]
        ys = np.minimum(((np.arange(size[1]) + 0.5) * h / size[1]).astype(np.int64), h - 1)
        xs = np.minimum(((np.arange(size[0]) + 0.5) * w / size[0]).astype(np.int64), w - 1)
        return a[ys][:, xs]
    h, w = a.shape[:2]
    if h % size[1] == 0 and w % size[0] == 0:  # whole-pixel boxes: PIL's box filter is the exact area average
        return np.asarray(Image.fromarray(a).resize(size, Image.Resampling.BOX))
    # PIL's box filter averages the source pixels whose centres fall in each target pixel's box: at a ratio that is
    # not whole (450 rows -> 112) the picture drifts by up to +-0.5 source px, in a sawtooth along the image, off
    # where K puts it; that biased the multi-view consistency of the nuScenes-like drive by -1.1 cm (docs/refine.md).
    # The exact area average: each target pixel is the mean of the source over its box, fractional pixels included.
    out = _area_mean(_area_mean(a.astype(np.float32), size[1], 0), size[0], 1)
    if a.dtype == np.uint8:
        return np.clip(np.rint(out), 0, 255).astype(np.uint8)
    return out.astype(a.dtype)


def _area_mean(a: np.ndarray, n: int, axis: int) -> np.ndarray:
    """``a`` resized to ``n`` samples along ``axis`` by the exact area average: the integral of the piecewise
    constant source (a cumulative sum, linear between pixel edges) differenced at the target boxes' edges."""
    m = a.shape[axis]
    c = np.concatenate([np.zeros_like(np.take(a, [0], axis)), np.cumsum(a, axis=axis, dtype=np.float64)], axis)
    edges = np.arange(n + 1) * (m / n)
    k = np.minimum(np.floor(edges).astype(np.int64), m - 1)
    shape = [1] * a.ndim
    shape[axis] = n + 1
    f = (edges - k).reshape(shape)
    integral = np.take(c, k, axis) + f * np.take(a, k, axis)
    d = np.diff(integral, axis=axis) / (m / n)
    return d.astype(np.float32)


def _depth_samples(dep: np.ndarray, size: tuple[int, int], scale: float) -> tuple[np.ndarray, np.ndarray]:
    """Sparse depth (H, W) -> per target pixel (h, w) the depth of its source sample nearest to the pixel
    centre (0 where none) and that sample's exact target coordinates (h, w, 2) float (u, v).

    Picking the one source pixel under each target centre would keep only ~scale^2 of the LiDAR returns,
    and render them half a source pixel off their ray (a bias of ~0.2 m in depth at 20 m at scale 0.25).
    Here every target pixel that holds a return keeps one, and its ray goes through the return itself:
    ``u' = sx (u + 0.5) - 0.5`` with each axis's true factor, the target size over the source's
    (pixel-centre convention of :meth:`Camera.scaled`, which scales K by the same factors; ``scale`` rounded a
    size, e.g. 450 rows at 0.25 -> 112, so the factor can differ from it).
    """
    w, h = size
    sx, sy = w / dep.shape[1], h / dep.shape[0]
    ys, xs = np.nonzero(dep > 0)
    out = np.zeros((h, w), np.float32)
    uv = np.stack(np.meshgrid(np.arange(w), np.arange(h)), -1).astype(np.float32)
    if ys.size == 0:
        return out, uv
    ut = sx * (xs + 0.5) - 0.5
    vt = sy * (ys + 0.5) - 0.5
    tx = np.clip(np.rint(ut), 0, w - 1).astype(np.int64)
    ty = np.clip(np.rint(vt), 0, h - 1).astype(np.int64)
    key = ty * w + tx
    order = np.lexsort(((ut - tx) ** 2 + (vt - ty) ** 2, key))  # by target pixel, then nearest first
    first = order[np.unique(key[order], return_index=True)[1]]
    out[ty[first], tx[first]] = dep[ys[first], xs[first]]
    uv[ty[first], tx[first], 0] = ut[first]
    uv[ty[first], tx[first], 1] = vt[first]
    return out, uv


class ScaledImages:
    """Views' RGB images handed from an earlier reader to :func:`build_pool` at the pool's scale, so that no
    image is decoded twice (the ground points read every training view at full resolution; a PNG costs
    ~10 ms). Holds (H, W, 3) uint8 at ``scale`` per image path until taken."""

    def __init__(self, seq: Sequence, scale: float):
        self.seq, self.scale = seq, scale
        self.rgb: dict[str, np.ndarray] = {}

    def put(self, view: View, rgb: np.ndarray) -> None:
        """Keep ``rgb`` (H, W, 3) uint8, the full-resolution image of ``view``, resized to the pool's scale."""
        cam = self.seq.cameras[view.camera].scaled(self.scale)
        self.rgb[view.image] = _resize(rgb, (cam.width, cam.height), nearest=False)

    def take(self, view: View) -> np.ndarray | None:
        return self.rgb.pop(view.image, None)


def build_pool(seq: Sequence, views: list[tuple[int, View]], scale: float, channel_lut: np.ndarray,
               use_semantics: bool, use_depth: bool, images: ScaledImages | None = None) -> PixelPool:
    """Load, resize and flatten views. channel_lut (256,) int: class id -> semantic channel (-1 unknown).
    ``images``: views already read at this ``scale``, taken from there instead of decoded again."""
    movable, sky, road = seq.class_lut("movable"), seq.class_lut("sky"), seq.class_lut("road")
    ground = seq.class_lut("ground")
    keys, K, T = [], [], []
    cols: dict[str, list[np.ndarray]] = {k: [] for k in ("view", "uv", "rgb", "ch", "road", "depth")}
    for vi, (frame_index, v) in enumerate(views):
        cam = seq.cameras[v.camera].scaled(scale)
        size = (cam.width, cam.height)
        rgb = images.take(v) if images is not None and images.scale == scale else None
        if rgb is None or rgb.shape[:2] != size[::-1]:
            rgb = _resize(load_rgb(seq.path(v.image)), size, nearest=False)
        if use_semantics and v.semantics:
            lab = _resize(load_semantics(seq.path(v.semantics)), size, nearest=True)
            keep = ~(movable[lab] | sky[lab])
            ch = channel_lut[lab]
            rd = road[lab]
        else:
            keep = np.ones(size[::-1], dtype=bool)
            ch = np.full(size[::-1], -1, dtype=np.int64)
            rd = np.ones(size[::-1], dtype=bool)  # without semantics the mesh footprint is the road
        ego = ego_mask_at(seq, v.camera, size[0], size[1])
        if ego is not None:  # the bonnet moves with the camera: its pixels are not road at any height
            keep = keep & ~ego
        uvmap = None
        if use_depth and v.depth:
            raw = load_depth(seq.path(v.depth))
            if raw.shape[1] == size[0] and raw.shape[0] == size[1]:
                dep = raw
            else:
                dep, uvmap = _depth_samples(raw, size, scale)
        else:
            dep = np.zeros(size[::-1], dtype=np.float32)
        if use_semantics and v.semantics:
            # Depth on a building or a pole says nothing about the road's height; under an object standing on
            # the ground, its lower part would lift the surface (a 0.1-0.3 m bump the size of the object).
            dep = np.where(ground[lab], dep, 0.0).astype(np.float32)
        yy, xx = np.nonzero(keep)
        keys.append(ViewKey(frame_index, v.camera))
        K.append(cam.K)
        T.append(v.T_world_cam)
        cols["view"].append(np.full(yy.size, vi, dtype=np.int64))
        cols["uv"].append(np.stack([xx, yy], 1).astype(np.float32) if uvmap is None else uvmap[yy, xx])
        cols["rgb"].append(rgb[yy, xx])
        cols["ch"].append(ch[yy, xx].astype(np.int64))
        cols["road"].append(rd[yy, xx])
        cols["depth"].append(dep[yy, xx].astype(np.float32))
    cat = {k: (np.concatenate(v) if v else np.zeros(0)) for k, v in cols.items()}
    has_depth = use_depth and any(v.depth for _, v in views)
    return PixelPool(
        keys,
        torch.tensor(np.array(K), dtype=torch.float32).reshape(-1, 3, 3),
        torch.tensor(np.array(T), dtype=torch.float32).reshape(-1, 4, 4),
        torch.from_numpy(cat["view"].astype(np.int64)),
        torch.from_numpy(cat["uv"].astype(np.float32).reshape(-1, 2)),
        torch.from_numpy(cat["rgb"].astype(np.uint8).reshape(-1, 3)),
        torch.from_numpy(cat["ch"].astype(np.int64)),
        torch.from_numpy(cat["road"].astype(bool)),
        torch.from_numpy(cat["depth"].astype(np.float32)) if has_depth else None,
    )


def split_frames(n_frames: int, holdout_every: int, stride: int) -> tuple[list[int], list[int]]:
    """Positions of training and held-out frames. Every k-th frame (positions k//2, k//2 + k, ...) is
    held out; training takes every ``stride``-th of the rest. Fewer than 2 frames: nothing held out."""
    pos = list(range(n_frames))
    if holdout_every > 0 and n_frames >= 2:
        k = holdout_every
        held = [p for p in pos if p % k == k // 2] if k > 1 else pos[1::2]
    else:
        held = []
    rest = [p for p in pos if p not in set(held)]
    return rest[::stride], held


def finite_views(seq: Sequence, positions: list[int]) -> tuple[list[tuple[int, View]], int]:
    """Views of the frames at ``positions`` whose pose is finite; also the number dropped."""
    out, dropped = [], 0
    for p in positions:
        f = seq.frames[p]
        for v in f.views.values():
            T = np.asarray(v.T_world_cam, dtype=np.float64)
            if T.shape == (4, 4) and np.all(np.isfinite(T)) and math.isfinite(float(np.linalg.det(T[:3, :3]))):
                out.append((f.index, v))
            else:
                dropped += 1
    return out, dropped
