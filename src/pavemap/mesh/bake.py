"""Closed-form vertex colours on a fixed surface ("baking"), used to start and to finish stage-1 training.

With the surface fixed, the per-vertex colours that minimise ``sum_p sum_k b_pk ||c_k - I_p||^2`` (every
training pixel ``p`` pulls each vertex ``k`` of its triangle towards its colour ``I_p`` with its barycentric
weight ``b_pk``; by Jensen an upper bound of the rendered L2 loss) are the weighted means
``c_k = sum_p b_pk I_p / sum_p b_pk``. One pass over the pixels gives them. Why we need it: sparse Adam
at the SPEC's rate 0.1 moves each colour by about 0.1 per step and, in the ~140 steps a CPU run affords,
leaves the colours noisier than the same surface supports (docs/history, stage 1), and vertices that no
training pixel hits keep their N(0, 0.01) start: black spots where a held-out view sees them.
Those are filled from their neighbours by normalised Gaussian smoothing.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import NamedTuple

import torch
from torch.nn import functional as F  # noqa: N812

from pavemap.geometry import HeightField, find_hits, hits_to_rayhit, surface_bounds
from pavemap.mesh import exposure as exposure_model
from pavemap.mesh.data import PixelPool
from pavemap.mesh.model import RoadMeshModel
from pavemap.mesh.render import view_rays


def _gaussian_blur(x: torch.Tensor, sigma: float) -> torch.Tensor:
    """(C, ny, nx) -> same, separable Gaussian with zero padding (the normalisation divides it out)."""
    r = max(1, int(3 * sigma + 0.5))
    t = torch.arange(-r, r + 1, dtype=x.dtype, device=x.device)
    k = torch.exp(-0.5 * (t / sigma) ** 2)
    k = k / k.sum()
    c = x.shape[0]
    y = F.conv2d(x[:, None], k.reshape(1, 1, 1, -1).expand(1, 1, 1, -1), padding=(0, r))
    y = F.conv2d(y, k.reshape(1, 1, -1, 1), padding=(r, 0))
    return y.reshape(c, *x.shape[1:])


def pool_hits(surface: HeightField, pool: PixelPool, T: torch.Tensor, max_dist: float, batch: int
               ) -> Iterator[tuple[slice, torch.Tensor, torch.Tensor, torch.Tensor]]:
    """Per batch of pool pixels that hit the surface: (the batch's slice, hit rows (M,) within it, their
    triangles' flat vertex ids (M, 3), barycentric weights (M, 3) float64)."""
    nx = surface.heights.shape[1]
    bounds = surface_bounds(surface, pool.uv.dtype)
    for s in range(0, len(pool), batch):
        sl = slice(s, s + batch)
        o, d = view_rays(pool.K, T, pool.view[sl], pool.uv[sl])
        cells = find_hits(surface, o, d, max_dist, bounds=bounds)
        if cells.idx.numel() == 0:
            continue
        hit = hits_to_rayhit(surface, o, d, cells)
        yield sl, cells.idx, cells.vertex_ids(nx), hit.bary[cells.idx].double()


class Hits(NamedTuple):
    """The pool pixels that hit the surface, cached for repeated passes: flat vertex ids (M, 3), barycentric
    weights (M, 3) float32, colours (M, 3) uint8, their views (M,) long, semantic channels (M,) long
    (-1 unknown) and rows (M,) long in the pool, or None where not known (one batch of a march)."""

    vid: torch.Tensor
    w: torch.Tensor
    c8: torch.Tensor
    view: torch.Tensor
    channel: torch.Tensor
    rows: torch.Tensor | None = None


def batch_hits(pool: PixelPool, sl: slice, rows: torch.Tensor, vid: torch.Tensor, w: torch.Tensor) -> Hits:
    """One :func:`pool_hits` batch as the bake keeps it."""
    return Hits(vid, w.float(), pool.rgb[sl][rows], pool.view[sl][rows], pool.channel[sl][rows], sl.start + rows)


def march_pool(surface: HeightField, pool: PixelPool, T: torch.Tensor, max_dist: float,
               batch: int = 262144) -> list[Hits]:
    """Every pool pixel that hits ``surface`` from poses T, batch by batch (what a bake averages)."""
    return [batch_hits(pool, sl, rows, vid, w) for sl, rows, vid, w in pool_hits(surface, pool, T, max_dist, batch)]


def ground_hits(hits: list[Hits], ground: torch.Tensor | None) -> list[Hits]:
    """The ``hits`` of pixels that may colour the surface: ``ground`` (C,) bool per semantic channel, and the
    unlabelled pixels (channel -1); all of them when ``ground`` is None."""
    if ground is None:
        return hits
    out = []
    for h in hits:
        k = (h.channel < 0) | ground.to(h.channel.device)[h.channel.clamp_min(0)]
        out.append(Hits(h.vid[k], h.w[k], h.c8[k], h.view[k], h.channel[k], None if h.rows is None else h.rows[k]))
    return out


def _mean_colours(hits: list[Hits], n: int, exposure: torch.Tensor | None, device: torch.device
                  ) -> tuple[torch.Tensor, torch.Tensor]:
    """(n, 3) float64 weighted-mean colours of the compensated pixels and (n,) their summed weights."""
    acc = torch.zeros(n, 4, dtype=torch.float64, device=device)
    for h in hits:
        col = exposure_model.compensate(h.c8.double() / 255.0, exposure, h.view)
        vals = torch.cat([col, torch.ones_like(col[:, :1])], 1)  # (M, 4): rgb and a count
        acc.index_add_(0, h.vid.reshape(-1), (vals[:, None, :] * h.w.double()[..., None]).reshape(-1, 4))
    support = acc[:, 3]
    return acc[:, :3] / support.clamp_min(1e-12)[:, None], support


def bake_semantics(hits: list[Hits], n: int, n_classes: int, prior: float = 0.5) -> tuple[torch.Tensor, torch.Tensor]:
    """(n, C) float32 closed-form semantic logits of the grid vertices and (n,) bool: the vertices a labelled
    pixel reaches.

    With the surface fixed, per-vertex logits that minimise the pixels' cross-entropy, each pixel voting for
    the vertices of its triangle with its barycentric weight, are the log class frequencies of those votes;
    ``prior`` (a vote per class) keeps a vertex seen by one pixel from certainty. Why: Adam at the SPEC's
    rate needs epochs to move logits from zero, and the off-road filter of stage 2 reads these labels."""
    dev = hits[0].vid.device if hits else torch.device("cpu")
    votes = torch.zeros(n, n_classes, dtype=torch.float64, device=dev)
    for h in hits:
        lab = h.channel >= 0
        if not bool(lab.any()):
            continue
        vid, w = h.vid[lab], h.w[lab].double()
        flat = (vid * n_classes + h.channel[lab, None]).reshape(-1)
        votes.view(-1).index_add_(0, flat, w.reshape(-1))
    total = votes.sum(1)
    logits = torch.log((votes + prior) / (total[:, None] + prior * n_classes))
    return logits.float(), total > 0


def _fit_exposure(hits: list[Hits], rgb: torch.Tensor, n_views: int) -> torch.Tensor:
    pred = torch.cat([(h.w.double()[..., None] * rgb[h.vid]).sum(1) for h in hits])
    obs = torch.cat([h.c8.double() / 255.0 for h in hits])
    return exposure_model.fit(torch.cat([h.view for h in hits]), pred, obs, n_views)


@torch.no_grad()
def bake_exposed(surface: HeightField, pool: PixelPool, T: torch.Tensor, max_dist: float, fill_sigma: float = 1.0,
                 batch: int = 262144, sharpen_iters: int = 0, exposure_rounds: int = 0,
                 hits: list[Hits] | None = None, ground: torch.Tensor | None = None
                 ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """:func:`bake_colours` with the views' exposures (:mod:`pavemap.mesh.exposure`) fitted alongside:
    ``exposure_rounds`` alternations of baking the compensated colours and fitting each view's gain and
    offset to the texture. Returns rgb, support, coloured as :func:`bake_colours` and the exposure (V, 2)
    float64 of the pool's views (None with 0 rounds). One march over the pixels, cached; ``hits``: that
    march already made (:func:`march_pool` of this surface, pool and T), not repeated. ``ground``: (C,) bool
    per semantic channel, the classes whose pixels colour it (:func:`ground_hits`; None: every pixel)."""
    heights = surface.heights
    ny, nx = heights.shape
    hits = ground_hits(march_pool(surface, pool, T, max_dist, batch) if hits is None else hits, ground)
    exposure = None
    rgb, support = _mean_colours(hits, ny * nx, exposure, heights.device)
    for _ in range(exposure_rounds if hits else 0):  # no pixel on the surface: nothing to fit
        exposure = _fit_exposure(hits, rgb, len(pool.keys))
        rgb, support = _mean_colours(hits, ny * nx, exposure, heights.device)
    seen = support > 0
    cols = [exposure_model.compensate(h.c8.double() / 255.0, exposure, h.view) for h in hits] if sharpen_iters else []
    for _ in range(sharpen_iters):
        upd = torch.zeros(ny * nx, 3, dtype=torch.float64, device=heights.device)
        for h, col in zip(hits, cols, strict=True):
            w = h.w.double()
            r = col - (w[..., None] * rgb[h.vid]).sum(1)  # (M, 3) residuals
            upd.index_add_(0, h.vid.reshape(-1), (w[..., None] * r[:, None, :]).reshape(-1, 3))
        rgb = torch.where(seen[:, None], rgb + upd / support.clamp_min(1e-12)[:, None], rgb)
    rgb, support, coloured = _fill_unseen(rgb.reshape(ny, nx, 3), support.reshape(ny, nx), fill_sigma)
    return rgb, support, coloured, exposure


def _fill_unseen(rgb: torch.Tensor, support: torch.Tensor, fill_sigma: float
                 ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Vertices without support take the normalised Gaussian average of their neighbours' colours."""
    acc = torch.cat([rgb * support[..., None], support[..., None]], 2)
    blurred = _gaussian_blur(acc.permute(2, 0, 1), fill_sigma)
    fill_w = blurred[3]
    fill = (blurred[:3] / fill_w.clamp_min(1e-12)).permute(1, 2, 0)
    coloured = (support > 0) | (fill_w > 1e-9)
    rgb = torch.where((support > 0)[..., None], rgb, torch.where((fill_w > 1e-9)[..., None], fill, 0.0))
    return rgb.clamp(0, 1).float(), support.float(), coloured


@torch.no_grad()
def bake_colours(surface: HeightField, pool: PixelPool, T: torch.Tensor, max_dist: float, fill_sigma: float = 1.0,
                 batch: int = 262144, sharpen_iters: int = 0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Weighted-mean colours of the grid vertices from the pool's pixels on a fixed surface.

    surface: float32 dense heights (ny, nx) and bool crop; T: (V, 4, 4) camera-to-world poses
    of the pool's views (refined ones where pose refinement runs). Returns ``rgb`` (ny, nx, 3) float32 in
    [0, 1], ``support`` (ny, nx) float32, the summed barycentric weight of the pixels behind each vertex
    (0: no view sees it), and ``coloured`` (ny, nx) bool. Vertices without support get the normalised
    Gaussian (``fill_sigma`` cells) average of their neighbours; where even that is empty, ``coloured`` is
    False and the colour 0: the caller keeps its own value there.

    ``sharpen_iters``: that many Jacobi steps towards the exact least-squares colours, ``c += (sum_p b_pk r_p)
    / (sum_p b_pk)`` with ``r_p`` the pixel's residual on the current colours. The weighted mean blurs
    (each pixel is spread over its triangle's three vertices); the exact solution overfits single pixels
    (held-out PSNR per number of steps: docs/history, stage 1).
    """
    rgb, support, coloured, _ = bake_exposed(surface, pool, T, max_dist, fill_sigma, batch, sharpen_iters)
    return rgb, support, coloured


@torch.no_grad()
def pixel_residuals(surface: HeightField, pool: PixelPool, T: torch.Tensor, max_dist: float, rgb: torch.Tensor,
                    batch: int = 262144) -> torch.Tensor:
    """(N,) float32 colour distance (RGB in [0, 1], Euclidean) between each pool pixel and the surface's colour
    where its ray lands, interpolated from the vertex colours ``rgb`` (ny, nx, 3); NaN where the ray misses."""
    flat = rgb.reshape(-1, 3).double()
    out = torch.full((len(pool),), float("nan"), dtype=torch.float32, device=rgb.device)
    for sl, rows, vid, w in pool_hits(surface, pool, T, max_dist, batch):
        pred = (w[..., None] * flat[vid]).sum(1)
        r = torch.linalg.norm(pool.rgb[sl][rows].double() / 255.0 - pred, dim=1)
        out[sl.start + rows] = r.float()
    return out


@torch.no_grad()
def static_pixels(surface: HeightField, pool: PixelPool, T: torch.Tensor, max_dist: float, cutoff: float,
                  rounds: int = 2, fill_sigma: float = 1.0, blob_px: int = 0) -> torch.Tensor:
    """(N,) bool: the pool pixels that agree with the road the other views see; False for a moving object.

    A vehicle passing the camera covers a road vertex in a few views only: bake the colours, drop the pixels
    whose colour is more than ``cutoff`` (RGB distance in [0, 1]) from the baked road where they land, and
    bake again without them (``rounds`` times), so the majority of views decides. Pixels that miss the surface
    stay True (they are not evidence either way). ``blob_px`` > 0: only blobs at least 2 ``blob_px`` + 1 pixels
    wide in their image are dropped (:func:`_opened`).
    """
    keep = torch.ones(len(pool), dtype=torch.bool, device=pool.view.device)
    for _ in range(rounds):
        rgb, _, _ = bake_colours(surface, pool.subset(keep), T, max_dist, fill_sigma)
        r = pixel_residuals(surface, pool, T, max_dist, rgb)
        off = r > cutoff  # NaN (a miss) compares False: kept
        keep = ~(_opened(off, pool, blob_px) if blob_px > 0 else off)
    return keep


def _opened(flag: torch.Tensor, pool: PixelPool, radius: int) -> torch.Tensor:
    """(P,) bool: ``flag`` (P,) opened in each view's image by a (2 radius + 1)² square: only blobs that wide stay.

    A vehicle covers a blob of the image; a surface a centimetre off or a view's shading moves the colours at
    paint edges and texture, thin lines that the opening removes. Pixels not in the pool (sky, movable
    classes) count as flagged, so a blob is not eaten from the mask's border.
    """
    if not bool(flag.any()):
        return flag
    col = pool.uv[:, 0].floor().long().clamp(min=0)
    row = pool.uv[:, 1].floor().long().clamp(min=0)
    H, W = int(row.max()) + 1, int(col.max()) + 1
    k = 2 * radius + 1
    out = torch.zeros_like(flag)
    chunk = max(1, (16 << 20) // (4 * H * W))  # views a 16 MiB canvas holds (four live at once): a drive has thousands
    for v0 in range(0, len(pool.keys), chunk):
        sel = (pool.view >= v0) & (pool.view < v0 + chunk)
        img = torch.ones(chunk, 1, H, W, device=flag.device)
        img[pool.view[sel] - v0, 0, row[sel], col[sel]] = flag[sel].float()
        eroded = -torch.nn.functional.max_pool2d(-img, k, stride=1, padding=radius)
        opened = torch.nn.functional.max_pool2d(eroded, k, stride=1, padding=radius)
        out[sel] = opened[pool.view[sel] - v0, 0, row[sel], col[sel]] > 0.5
    return flag & out


@torch.no_grad()
def bake_into(model: RoadMeshModel, pool: PixelPool, T: torch.Tensor, fill: float, max_dist: float,
              fill_sigma: float = 1.0, sharpen_iters: int = 0, exposure_rounds: int = 0,
              hits: list[Hits] | None = None, semantics: bool = False, ground: torch.Tensor | None = None
              ) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Replace the model's vertex colours by the baked ones on its current surface (where any pixel reaches
    them, directly or through the gap fill), seen from poses T (V, 4, 4); ``fill`` is the height off the crop.
    Returns (Nv,) bool: the vertices some training pixel sees, and the views' exposure (V, 2) or None
    (``exposure_rounds``: :func:`bake_exposed`). ``hits``: the march of ``pool`` from T on the current surface
    when one was made already (:func:`pavemap.mesh.setup.visible_pixels`). ``semantics``: the vertices' semantic
    logits are baked too (:func:`bake_semantics`) where a labelled pixel reaches them. ``ground``: the semantic
    channels whose pixels colour the surface (:func:`ground_hits`; the semantics take every pixel)."""
    field = model.field(model.dense_heights(fill))
    if hits is None:
        hits = march_pool(field, pool, T, max_dist)
    rgb, support, coloured, exposure = bake_exposed(field, pool, T, max_dist, fill_sigma, sharpen_iters=sharpen_iters,
                                                    exposure_rounds=exposure_rounds, hits=hits, ground=ground)
    flat = model.vertex_flat_ids
    ok = coloured.reshape(-1)[flat]
    model.rgb.data[ok] = rgb.reshape(-1, 3)[flat][ok].to(model.rgb.dtype)
    if semantics and model.sem.shape[1]:
        logits, labelled = bake_semantics(hits, rgb.shape[0] * rgb.shape[1], model.sem.shape[1])
        got = labelled[flat]
        model.sem.data[got] = logits[flat][got].to(model.sem.dtype)
    return support.reshape(-1)[flat] > 0, exposure
