"""The road surface as a height field on a regular grid, and exact ray / surface intersection.

Triangulation (DESIGN, "The height-field renderer"): every cell ``(i, j)`` is split along the
diagonal from vertex ``(i, j)`` to ``(i+1, j+1)``; a triangle exists only where all three of its vertices
are ``valid`` (the trajectory crop). With local coordinates ``fx, fy`` in the cell:

- lower triangle (``fx >= fy``): vertices ``(i,j), (i+1,j), (i+1,j+1)``, weights ``(1-fx, fx-fy, fy)``
- upper triangle (``fx < fy``):  vertices ``(i,j), (i+1,j+1), (i,j+1)``, weights ``(1-fy, fx, fy-fx)``

Intersection of a ray ``p(lam) = o + lam d`` with the surface solves ``g(lam) = z(lam) - h(xy(lam)) = 0``
for the first root: a march along the ray's ground track at half-cell steps, restricted to the
part of the ray between the surface's lowest and highest point, finds the first interval where the
ray goes from above to below the surface; inside it, bisection plus an exact plane solve in the
triangle under the interval's end gives the root. All without autograd; one last Newton step with
autograd (exact, since ``g`` is linear inside a triangle) then makes ``lam``, the barycentric weights
and the points differentiable w.r.t. the heights, the origins and the directions (implicit function
theorem at the root).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch.nn import functional as F  # noqa: N812

from pavemap.geometry import march_cpu
from pavemap.geometry.grid import GridSpec


@dataclass
class HeightField:
    """Heights on a regular grid. Vertex ``(i=col, j=row)`` lies at ``(x0 + i*res, y0 + j*res)``.

    heights: (ny, nx) float32 (may require grad); valid: (ny, nx) bool, the vertices kept by the crop.
    """

    x0: float
    y0: float
    res: float
    heights: torch.Tensor
    valid: torch.Tensor

    @property
    def ny(self) -> int:
        return int(self.heights.shape[0])

    @property
    def nx(self) -> int:
        return int(self.heights.shape[1])

    @property
    def grid(self) -> GridSpec:
        """The vertex grid (origin, step, size) of this field."""
        return GridSpec(self.x0, self.y0, self.res, self.nx, self.ny)

    @property
    def extent(self) -> tuple[float, float, float, float]:
        """(x_min, x_max, y_min, y_max) of the vertex grid in world metres."""
        return (self.x0, self.x0 + (self.nx - 1) * self.res, self.y0, self.y0 + (self.ny - 1) * self.res)

    def to(self, device: torch.device | str) -> HeightField:
        return HeightField(self.x0, self.y0, self.res, self.heights.to(device), self.valid.to(device))

    def grid_xy(self) -> torch.Tensor:
        """(ny, nx, 2) world x, y of every vertex, dtype/device of ``heights``."""
        h = self.heights
        xs = self.x0 + self.res * torch.arange(self.nx, device=h.device, dtype=h.dtype)
        ys = self.y0 + self.res * torch.arange(self.ny, device=h.device, dtype=h.dtype)
        yy, xx = torch.meshgrid(ys, xs, indexing="ij")
        return torch.stack([xx, yy], dim=-1)

    def vertices(self) -> torch.Tensor:
        """(ny*nx, 3) world vertices, flat id ``j*nx + i`` (invalid vertices included)."""
        return torch.cat([self.grid_xy().reshape(-1, 2), self.heights.reshape(-1, 1)], dim=1)

    def faces(self, valid_only: bool = True) -> torch.Tensor:
        """(F, 3) long vertex ids of the triangles, counter-clockwise seen from above (+z)."""
        nx, ny = self.nx, self.ny
        dev = self.heights.device
        v = self.valid.to(dev) if valid_only else torch.ones((ny, nx), dtype=torch.bool, device=dev)
        quad = v[:-1, :-1] & v[1:, 1:]  # only the kept triangles are built: a long drive's grid is mostly empty
        tris = []
        for keep, a, b in ((quad & v[:-1, 1:], 1, nx + 1), (quad & v[1:, :-1], nx + 1, nx)):
            jj, ii = torch.nonzero(keep, as_tuple=True)
            tris.append(torch.stack([jj * nx + ii, jj * nx + ii + a, jj * nx + ii + b], 1))
        return torch.cat(tris, 0)

    def height_at(self, xy: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Interpolated surface height at world points xy (N, 2) -> z (N,), inside (N,) bool.

        ``inside`` is False off the grid or on a triangle with an invalid vertex (z is then 0).
        Differentiable w.r.t. ``heights`` and ``xy``.
        """
        u = (xy[:, 0] - self.x0) / self.res
        v = (xy[:, 1] - self.y0) / self.res
        ids, w, _, _, _, inside = _triangle(self, u, v)
        inside = inside & self.valid.reshape(-1)[ids].all(dim=1)
        z = (w * self.heights.reshape(-1)[ids].to(w.dtype)).sum(dim=1)
        return torch.where(inside, z, torch.zeros_like(z)), inside

    @classmethod
    def plane(cls, x0: float, y0: float, res: float, nx: int, ny: int, z: float = 0.0) -> HeightField:
        """A flat, fully valid field of nx by ny vertices at height z."""
        return cls(float(x0), float(y0), float(res), torch.full((ny, nx), float(z)),
                   torch.ones((ny, nx), dtype=torch.bool))


@dataclass
class RayHit:
    """First ray / surface intersections. Misses have hit False, lam 0, bary 0, vertex_ids 0.

    lam (N,) ray parameter (camera depth when dirs come from ``pixel_rays``); hit (N,) bool;
    points (N, 3); vertex_ids (N, 3) long flat ids ``j*nx+i``; bary (N, 3) weights of those vertices.
    """

    lam: torch.Tensor
    hit: torch.Tensor
    points: torch.Tensor
    vertex_ids: torch.Tensor
    bary: torch.Tensor

    def interpolate(self, attr: torch.Tensor) -> torch.Tensor:
        """Per-vertex attributes (ny*nx, C) or (ny, nx, C) -> (N, C) at the hits (0 for misses)."""
        a = attr.reshape(-1, attr.shape[-1])
        out = (self.bary[:, :, None].to(a.dtype) * a[self.vertex_ids]).sum(dim=1)
        return out * self.hit[:, None].to(out.dtype)


def _triangle(hf: HeightField, u: torch.Tensor, v: torch.Tensor, cell: tuple | None = None):
    """Triangle under grid coordinates (u, v) (any shape ``S``).

    Returns ids (S, 3) long, weights (S, 3), i (S,), j (S,), lower (S,) bool, inside_grid (S,) bool.
    With ``cell=(i, j, lower)`` the weights are those of that fixed triangle (affine, possibly
    outside [0, 1]); weights carry autograd from u, v.
    """
    nx, ny = hf.nx, hf.ny
    if cell is None:
        inside = (u >= 0) & (u <= nx - 1) & (v >= 0) & (v <= ny - 1)
        i = torch.floor(u.detach()).clamp(0, max(nx - 2, 0)).long()
        j = torch.floor(v.detach()).clamp(0, max(ny - 2, 0)).long()
        fx, fy = u - i, v - j
        lower = (fx >= fy).detach()
    else:
        i, j, lower = cell
        inside = torch.ones_like(lower)
        fx, fy = u - i, v - j
    w = torch.where(
        lower[..., None],
        torch.stack([1 - fx, fx - fy, fy], dim=-1),
        torch.stack([1 - fy, fx, fy - fx], dim=-1),
    )
    v00 = j * nx + i
    ids = torch.where(
        lower[..., None],
        torch.stack([v00, v00 + 1, v00 + nx + 1], dim=-1),
        torch.stack([v00, v00 + nx + 1, v00 + nx], dim=-1),
    )
    return ids, w, i, j, lower, inside


def _weight_slope(du: torch.Tensor, dv: torch.Tensor, lower: torch.Tensor) -> torch.Tensor:
    """d(weights)/d(lam) (S, 3) of the triangle type ``lower`` for grid-coordinate speeds du, dv."""
    return torch.where(
        lower[..., None],
        torch.stack([-du, du - dv, dv], dim=-1),
        torch.stack([-dv, du, dv - du], dim=-1),
    )


def _empty_hit(origins: torch.Tensor) -> RayHit:
    n = origins.shape[0]
    z = origins.new_zeros(n)
    return RayHit(z, torch.zeros(n, dtype=torch.bool, device=origins.device), origins.clone(),
                  torch.zeros(n, 3, dtype=torch.long, device=origins.device), origins.new_zeros(n, 3))


@dataclass
class SurfaceBounds:
    """What the march needs beyond the heights: flat heights (ny*nx,), flat crop (ny*nx,), global
    min/max (padded) and the dilated tile maxima (tny, tnx) for empty-space skipping."""

    H: torch.Tensor
    V: torch.Tensor
    hmin: torch.Tensor
    hmax: torch.Tensor
    tmax: torch.Tensor
    tile: int


@torch.no_grad()
def surface_bounds(hf: HeightField, dtype: torch.dtype | None = None, tile: int = 16) -> SurfaceBounds:
    """Precompute the march's bounds once per height field (O(grid)); reuse across many ray batches."""
    H = hf.heights.detach().to(dtype or hf.heights.dtype).reshape(-1)
    V = hf.valid.reshape(-1).to(H.device)
    hv = H[V]
    hmin, hmax = hv.min(), hv.max()
    pad = 1e-6 * (1.0 + torch.maximum(hmin.abs(), hmax.abs()))
    # The max over tiles of TILE x TILE vertices, dilated by one tile, bounds the surface within
    # TILE-1 cells (Chebyshev) of any point of a tile.
    Hm = torch.where(V, H, torch.full_like(H, -torch.inf)).reshape(1, 1, hf.ny, hf.nx)
    tmax = F.max_pool2d(Hm, tile, stride=tile, ceil_mode=True)
    tmax = F.max_pool2d(tmax, 3, stride=1, padding=1)[0, 0]
    return SurfaceBounds(H, V, hmin - pad, hmax + pad, tmax, tile)


@torch.no_grad()
def _find_roots(hf: HeightField, o: torch.Tensor, d: torch.Tensor, max_dist: float, step: float,
                chunk: int, refine_iters: int, bounds: SurfaceBounds | None = None):
    """Without autograd: (idx of hit rays, lam0, i, j, lower) for the first crossing of each ray."""
    dev, dt = o.device, o.dtype
    n = o.shape[0]
    if bounds is None or bounds.H.dtype != dt:
        bounds = surface_bounds(hf, dt)
    H, V, hmin, hmax = bounds.H, bounds.V, bounds.hmin, bounds.hmax

    lo = torch.zeros(n, dtype=dt, device=dev)
    hi = torch.full((n,), float(max_dist), dtype=dt, device=dev)
    # Only the part of the ray between the surface's lowest and highest point can cross it.
    dz = d[:, 2]
    moving = dz.abs() > 1e-12
    safe_dz = torch.where(moving, dz, torch.ones_like(dz))
    l1, l2 = (hmin - o[:, 2]) / safe_dz, (hmax - o[:, 2]) / safe_dz
    lo = torch.where(moving, torch.maximum(lo, torch.minimum(l1, l2)), lo)
    hi = torch.where(moving, torch.minimum(hi, torch.maximum(l1, l2)), hi)
    flat_out = ~moving & ((o[:, 2] < hmin) | (o[:, 2] > hmax))
    hi = torch.where(flat_out, torch.full_like(hi, -1.0), hi)
    # ... and inside the grid's xy box (slab test).
    x_min, x_max, y_min, y_max = hf.extent
    for ax, (a0, a1) in ((0, (x_min, x_max)), (1, (y_min, y_max))):
        da = d[:, ax]
        mv = da.abs() > 1e-12
        sda = torch.where(mv, da, torch.ones_like(da))
        t1, t2 = (a0 - o[:, ax]) / sda, (a1 - o[:, ax]) / sda
        lo = torch.where(mv, torch.maximum(lo, torch.minimum(t1, t2)), lo)
        hi = torch.where(mv, torch.minimum(hi, torch.maximum(t1, t2)), hi)
        out = ~mv & ((o[:, ax] < a0) | (o[:, ax] > a1))
        hi = torch.where(out, torch.full_like(hi, -1.0), hi)

    u0 = (o[:, 0] - hf.x0) / hf.res
    v0 = (o[:, 1] - hf.y0) / hf.res
    du, dv = d[:, 0] / hf.res, d[:, 1] / hf.res
    # Lambda step that moves at most `step` cells along either grid axis.
    speed = torch.maximum(du.abs(), dv.abs()).clamp_min(1e-12)
    dl = step / speed
    # A ray that never moves horizontally (straight down) needs just its two bracket ends.
    dl = torch.minimum(dl, (hi - lo).clamp_min(1e-12))

    def g_at(rows: torch.Tensor, lam: torch.Tensor):
        """(g, valid) at rays ``rows`` (R,) and parameters lam (R, M)."""
        uu = u0[rows, None] + lam * du[rows, None]
        vv = v0[rows, None] + lam * dv[rows, None]
        ids, w, _, _, _, inside = _triangle(hf, uu, vv)
        ok = inside & V[ids].all(dim=-1)
        g = o[rows, 2, None] + lam * d[rows, 2, None] - (w * H[ids]).sum(dim=-1)
        return g, ok

    # Empty-space skipping: the max height over tiles of TILE x TILE cells, dilated by one tile, bounds
    # the surface within TILE-1 cells (Chebyshev) of any point. Where the ray is above that bound it
    # advances by a safe step; near the surface it samples at `step`-cell spacing.
    tile, tmax = bounds.tile, bounds.tmax
    tny, tnx = tmax.shape
    reach = float(tile - 1)

    found = torch.zeros(n, dtype=torch.bool, device=dev)
    a_br = torch.zeros(n, dtype=dt, device=dev)
    b_br = torch.zeros(n, dtype=dt, device=dev)
    cur = lo.clone()
    rows = torch.nonzero(lo <= hi).squeeze(1)
    ks = torch.arange(chunk + 1, device=dev, dtype=dt)
    while rows.numel():
        lc = cur[rows]
        uu, vv = u0[rows] + lc * du[rows], v0[rows] + lc * dv[rows]
        tx = torch.floor(uu / tile).long().clamp(0, tnx - 1)
        ty = torch.floor(vv / tile).long().clamp(0, tny - 1)
        margin = o[rows, 2] + lc * d[rows, 2] - tmax[ty, tx]
        # skip: stay within `reach` cells and above the bound; worth it only beyond one fine chunk
        down = d[rows, 2] < 0
        adv = reach / speed[rows]
        adv = torch.where(down & (margin > 0), torch.minimum(adv, margin / (-d[rows, 2]).clamp_min(1e-30)), adv)
        skip = (margin > 0) & (adv >= chunk * dl[rows])
        srows = rows[skip]
        cur[srows] = lc[skip] + adv[skip]
        # fine: a chunk of samples from the current point
        frows = rows[~skip]
        if frows.numel():
            lam = torch.minimum(cur[frows, None] + ks * dl[frows, None], hi[frows, None])
            g, ok = g_at(frows, lam)
            above = (g >= 0) | ~ok
            below = ok & (g < 0)
            cross = above[:, :-1] & below[:, 1:]
            anyc = cross.any(dim=1)
            first = torch.argmax(cross.to(torch.uint8), dim=1)
            hit_rows = frows[anyc]
            found[hit_rows] = True
            a_br[hit_rows] = lam[anyc, first[anyc]]
            b_br[hit_rows] = lam[anyc, first[anyc] + 1]
            cur[frows] = torch.where(anyc, hi[frows] + 1.0, cur[frows] + chunk * dl[frows])
        rows = rows[(cur[rows] <= hi[rows]) & ~found[rows]]

    idx = torch.nonzero(found).squeeze(1)
    a, b = a_br[idx], b_br[idx]
    lam0 = b.clone()
    done = torch.zeros(idx.numel(), dtype=torch.bool, device=dev)
    ci = torch.zeros(idx.numel(), dtype=torch.long, device=dev)
    cj = torch.zeros_like(ci)
    clower = torch.zeros_like(done)
    for _ in range(refine_iters):
        act = torch.nonzero(~done).squeeze(1)
        if not act.numel():
            break
        r = idx[act]
        bb, aa = b[act], a[act]
        ub, vb = u0[r] + bb * du[r], v0[r] + bb * dv[r]
        ids, w, i, j, lower, _ = _triangle(hf, ub, vb)
        hb = H[ids]
        gb = o[r, 2] + bb * d[r, 2] - (w * hb).sum(-1)
        slope = d[r, 2] - (_weight_slope(du[r], dv[r], lower) * hb).sum(-1)
        safe = torch.where(slope.abs() > 1e-12, slope, torch.full_like(slope, -1e-12))
        lp = bb - gb / safe
        span = (bb - aa).abs() + 1e-9
        tol_l = 1e-7 * span + 1e-12
        up, vp = u0[r] + lp * du[r], v0[r] + lp * dv[r]
        _, wp, _, _, _, _ = _triangle(hf, up, vp, cell=(i, j, lower))
        conv = (slope < 0) & (lp >= aa - tol_l) & (lp <= bb + tol_l) & (wp >= -1e-6).all(-1)
        lam0[act[conv]] = lp[conv]
        ci[act[conv]], cj[act[conv]], clower[act[conv]] = i[conv], j[conv], lower[conv]
        done[act[conv]] = True
        # Bisect the rest, keeping "above at a, below at b".
        nc = ~conv
        m = 0.5 * (aa[nc] + bb[nc])
        gm, okm = g_at(r[nc], m[:, None])
        below_m = (okm & (gm < 0)).squeeze(1)
        sel = act[nc]
        b[sel] = torch.where(below_m, m, bb[nc])
        a[sel] = torch.where(below_m, aa[nc], m)
    # Rays that never converged pass under a crop edge (the crossing lies on a missing triangle):
    # they are misses, like a rasterizer that only draws the kept triangles.
    return idx[done], lam0[done], ci[done], cj[done], clower[done]


@dataclass
class HitCells:
    """Roots found without autograd: ray rows ``idx`` (M,) long that hit, their ``lam0`` (M,) and the
    triangle of each hit as cell column ``i`` (M,), row ``j`` (M,) and ``lower`` (M,) bool."""

    idx: torch.Tensor
    lam0: torch.Tensor
    i: torch.Tensor
    j: torch.Tensor
    lower: torch.Tensor

    def vertex_ids(self, nx: int) -> torch.Tensor:
        """(M, 3) long flat vertex ids of the hit triangles (same order as the barycentric weights)."""
        v00 = self.j * nx + self.i
        return torch.where(
            self.lower[:, None],
            torch.stack([v00, v00 + 1, v00 + nx + 1], dim=-1),
            torch.stack([v00, v00 + nx + 1, v00 + nx], dim=-1),
        )


def find_hits(
    hf: HeightField,
    origins: torch.Tensor,
    dirs: torch.Tensor,
    max_dist: float = 200.0,
    step: float = 0.5,
    chunk: int = 16,
    refine_iters: int = 40,
    max_rays_per_batch: int = 262144,
    bounds: SurfaceBounds | None = None,
) -> HitCells:
    """The no-autograd half of :func:`intersect_rays`: which rays hit, where, on which triangle.

    Split out so a caller can find the triangles on cached heights, then evaluate fresh heights only at the
    vertices it needs and call :func:`hits_to_rayhit` (stage-1 training). ``bounds`` from :func:`surface_bounds`
    (same heights, dtype of ``origins``) saves O(grid) work per call. On a CPU the march runs compiled.
    """
    n, dev = origins.shape[0], origins.device
    if n == 0 or not bool(hf.valid.any()) or hf.nx < 2 or hf.ny < 2:
        e = torch.zeros(0, dtype=torch.long, device=dev)
        return HitCells(e, origins.new_zeros(0).detach(), e, e.clone(), torch.zeros(0, dtype=torch.bool, device=dev))
    o_d, d_d = origins.detach(), dirs.detach()
    if bounds is None or bounds.H.dtype != o_d.dtype:
        bounds = surface_bounds(hf, o_d.dtype)
    roots = march_cpu.find_roots_cpu if march_cpu.use_for(o_d) else _find_roots  # same march, compiled
    parts = []
    for s in range(0, n, max_rays_per_batch):
        e = min(n, s + max_rays_per_batch)
        idx, lam0, i, j, lower = roots(hf, o_d[s:e], d_d[s:e], max_dist, step, chunk, refine_iters, bounds)
        parts.append((idx + s, lam0, i, j, lower))
    return HitCells(*(torch.cat([p[k] for p in parts]) for k in range(5)))


def hits_to_rayhit(hf: HeightField, origins: torch.Tensor, dirs: torch.Tensor, cells: HitCells) -> RayHit:
    """The autograd half of :func:`intersect_rays`: one exact Newton step on each hit's triangle.

    At a converged root its value is ``lam0`` and its derivative is that of the root (implicit
    function theorem), so lam, points and barycentric weights are differentiable w.r.t. ``hf.heights``
    (only the three vertices of each hit triangle are read), ``origins`` and ``dirs``. Weights are clipped at 0.
    """
    n = origins.shape[0]
    idx, lam0, i, j, lower = cells.idx, cells.lam0, cells.i, cells.j, cells.lower
    o, d = origins[idx], dirs[idx]
    dt = origins.dtype
    lam0 = lam0.to(dt)
    Hf = hf.heights.reshape(-1)
    u_fn = lambda lam: (o[:, 0] + lam * d[:, 0] - hf.x0) / hf.res  # noqa: E731
    v_fn = lambda lam: (o[:, 1] + lam * d[:, 1] - hf.y0) / hf.res  # noqa: E731
    ids, w0, _, _, _, _ = _triangle(hf, u_fn(lam0), v_fn(lam0), cell=(i, j, lower))
    h = Hf[ids].to(dt)
    g0 = o[:, 2] + lam0 * d[:, 2] - (w0 * h).sum(-1)
    slope = d[:, 2] - (_weight_slope(d[:, 0] / hf.res, d[:, 1] / hf.res, lower) * h).sum(-1)
    slope = torch.where(slope.abs() > 1e-12, slope, torch.full_like(slope, -1e-12))
    lam = lam0 - g0 / slope
    _, bary, _, _, _, _ = _triangle(hf, u_fn(lam), v_fn(lam), cell=(i, j, lower))
    bary = (b := bary.clamp_min(0.0)) / b.sum(-1, keepdim=True)  # -0.003 seen: a bake's votes
    pts = o + lam[:, None] * d

    hit = torch.zeros(n, dtype=torch.bool, device=origins.device)
    hit[idx] = True
    lam_full = origins.new_zeros(n).index_copy(0, idx, lam)
    pts_full = origins.index_copy(0, idx, pts) if idx.numel() else origins.clone()
    ids_full = torch.zeros(n, 3, dtype=torch.long, device=origins.device).index_copy(0, idx, ids)
    bary_full = origins.new_zeros(n, 3).index_copy(0, idx, bary.to(dt))
    return RayHit(lam_full, hit, pts_full, ids_full, bary_full)


def intersect_rays(
    hf: HeightField,
    origins: torch.Tensor,
    dirs: torch.Tensor,
    max_dist: float = 200.0,
    step: float = 0.5,
    chunk: int = 16,
    refine_iters: int = 40,
    max_rays_per_batch: int = 262144,
) -> RayHit:
    """First intersection of rays ``origins + lam * dirs`` (N, 3) with the surface, ``0 <= lam <= max_dist``.

    ``step`` is the march step in cells (0.5: a crossing is missed only where the ray clips the
    surface for less than half a cell, i.e. grazing a ridge). Differentiable w.r.t. ``hf.heights``,
    ``origins`` and ``dirs`` at the hits. Rays that point upward, leave the grid, or only meet the
    surface outside the crop are misses.
    """
    if origins.shape[0] == 0 or not bool(hf.valid.any()) or hf.nx < 2 or hf.ny < 2:
        return _empty_hit(origins)
    cells = find_hits(hf, origins, dirs, max_dist, step, chunk, refine_iters, max_rays_per_batch)
    return hits_to_rayhit(hf, origins, dirs, cells)
