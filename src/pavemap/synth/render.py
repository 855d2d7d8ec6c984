"""Renderer of the synthetic world, independent of any reconstruction code.

Per view it produces RGB, semantic labels, metric depth (camera z), a defect instance map and an
auxiliary code map (defect / off-road streak / cast shadow) that the simulated detector reads.
Rays come from :func:`pavemap.geometry.camera.pixel_rays`, hits from :mod:`pavemap.synth.raycast`;
shading is here. Everything is whole-image tensor code; no per-pixel Python.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from pavemap.device import resolve_device
from pavemap.geometry.camera import pixel_grid, pixel_rays
from pavemap.synth.clutter import box_corners
from pavemap.synth.params import (
    BUILDING,
    DECOY_ID_OFFSET,
    DEFAULT_THREADS,
    OBJECT_KINDS,
    ROAD,
    SKY,
    TERRAIN,
    torch_threads,
)
from pavemap.synth.raycast import BOX_EDGES, intersect_boxes, intersect_ground, intersect_spheres, screen_rects
from pavemap.synth.scene import World
from pavemap.synth.surface import bilinear_t, ground_label, markings, st_lookup, value_noise
from pavemap.types import Camera

SHADOW_BIT = 1 << 14
HORIZON = torch.tensor([0.80, 0.85, 0.9])
ZENITH = torch.tensor([0.40, 0.58, 0.84])


@dataclass
class RenderOutput:
    """One rendered view. All arrays (H, W)."""

    rgb: np.ndarray  # (H, W, 3) uint8
    label: np.ndarray  # (H, W) uint8 class ids (world.CLASSES)
    depth: np.ndarray  # (H, W) float32 camera-z metres, 0 where nothing was hit (sky)
    instance: np.ndarray  # (H, W) int32: 0 none, else defect id + 1 (visible, unoccluded pixels only)
    code: np.ndarray  # (H, W) uint16: low 14 bits defect id+1 or decoy+DECOY_ID_OFFSET; bit 14 shadow
    obj: np.ndarray  # (H, W) int32: 0 none, else object kind index + 1 (OBJECT_KINDS)


def _hash01(a: torch.Tensor, b: torch.Tensor, seed: float) -> torch.Tensor:
    """Deterministic pseudo-random value in [0, 1) per integer pair (for Voronoi jitter)."""
    v = torch.sin(a * 127.1 + b * 311.7 + seed * 74.7) * 43758.5453
    return v - v.floor()


# ---------------------------------------------------------------------------- shading


def _ground_shade(world: World, tw: dict, px, py, lam_fp):
    """Albedo (M, 3), label (M,), normal (M, 3), shadow (M,), code (M,) int for ground points."""
    p = world.params
    tiles = tw["tiles"]
    s, t = st_lookup(tw, px, py)
    _, hx, hy = bilinear_t(tw["height"], tw["hgrid"], px, py, grad=True)
    nrm = torch.stack([-hx, -hy, torch.ones_like(hx)], 1)
    nrm = nrm / nrm.norm(dim=1, keepdim=True)
    fp = lam_fp
    cov, paint = markings(p, s, t, fp)
    lab = ground_label(p, s, t, cov)

    def att(scale: float):
        return (scale / (2 * fp) - 1).clamp(0, 1)  # fade octaves finer than the pixel footprint

    n1 = value_noise(tiles[0], px, py, 5.0)
    n2 = value_noise(tiles[1], px, py, 1.1)
    n3 = value_noise(tiles[2], px, py, 0.21)
    n4 = value_noise(tiles[3], px, py, 0.045)
    grain = 0.07 * (n1 - 0.5) + 0.06 * (n2 - 0.5) + 0.07 * (n3 - 0.5) * att(0.21) + 0.1 * (n4 - 0.5) * att(0.045)
    # tyre tracks: slightly darker, polished bands in each lane
    lane_pos = torch.remainder(t + p.width / 2, p.lane_width) - p.lane_width / 2
    tracks = 0.035 * torch.exp(-(((lane_pos.abs() - 0.85) / 0.3) ** 2))
    asphalt = (0.40 + grain - tracks).clamp(0.05, 1)[:, None] * torch.tensor([1.0, 1.0, 1.035], device=px.device)
    wear = 0.8 + 0.2 * n3
    road_col = asphalt * (1 - (cov * wear)[:, None]) + paint * (cov * wear)[:, None]
    concrete = (0.62 + 0.08 * (n2 - 0.5) + 0.06 * (n4 - 0.5) * att(0.045))[:, None] * torch.tensor(
        [1.0, 0.99, 0.96], device=px.device)
    # sidewalk slabs: joints every 1.5 m along the road and one along the middle
    ms = torch.remainder(s, 1.5)
    jd = torch.minimum(ms, 1.5 - ms)
    joint = ((0.006 - jd) / fp.clamp(min=1e-3) + 0.5).clamp(0, 1) * (0.012 / fp).clamp(max=1)
    walk = (0.58 + 0.06 * (n2 - 0.5) + 0.08 * (n4 - 0.5) * att(0.045))[:, None] * torch.tensor(
        [1.0, 0.96, 0.9], device=px.device) * (1 - 0.35 * joint)[:, None]
    g_mix = (0.6 * n1 + 0.4 * n2)[:, None]
    grass = torch.tensor([0.22, 0.36, 0.13], device=px.device) * (0.7 + 0.6 * n3 * att(0.21) + 0.3 * n2)[:, None]
    dirt = torch.tensor([0.42, 0.35, 0.25], device=px.device) * (0.8 + 0.3 * n4)[:, None]
    terrain = grass * (1 - (g_mix - 0.55).clamp(0, 0.3) / 0.3) + dirt * ((g_mix - 0.55).clamp(0, 0.3) / 0.3)
    a = torch.abs(t)
    w2 = p.width / 2
    col = torch.where((a < w2)[:, None], road_col, terrain)
    sw = torch.where(t > 0, torch.full_like(t, p.sidewalk_left), torch.full_like(t, p.sidewalk_right))
    col = torch.where(((a >= w2) & (a < w2 + p.curb_width))[:, None], concrete, col)
    col = torch.where(((a >= w2 + p.curb_width) & (a < w2 + p.curb_width + sw))[:, None], walk, col)
    # gutter grime along the kerb
    grime = torch.exp(-(((a - w2 + 0.1) / 0.18) ** 2)) * (a < w2)
    col = col * (1 - 0.25 * grime * n2)[:, None]

    # ---- defects and off-road streaks (only where a point is inside an item's bounding box)
    code = torch.zeros_like(s, dtype=torch.long)
    it = tw["items"]
    if it["n"] > 0:
        nb = it["table"].shape[0]
        b = ((s - it["s_min"]) / it["bin_m"]).long().clamp(0, nb - 1)
        cand = it["table"][b]  # (M, K)
        ab = it["aabb"][cand.clamp(min=0)]
        inb = (cand >= 0) & (px[:, None] >= ab[..., 0]) & (py[:, None] >= ab[..., 1]) & (
            px[:, None] <= ab[..., 2]) & (py[:, None] <= ab[..., 3])
        pi, ki = torch.nonzero(inb, as_tuple=True)
        if pi.numel():
            item = cand[pi, ki]
            factor, member, darken_base = _item_effects(it, item, px[pi], py[pi], fp[pi], tiles)
            f = torch.ones_like(s).scatter_reduce_(0, pi, factor, reduce="prod")
            col = col * f[:, None]
            base = torch.ones_like(s).scatter_reduce_(0, pi, darken_base, reduce="prod")
            col = col * base[:, None] * torch.tensor([1.0, 0.98, 0.95], device=px.device).pow(
                (1 - base)[:, None] * 4)
            codes = torch.where(member, it["prm"][item, 1].long(), torch.zeros_like(item))
            code.scatter_reduce_(0, pi, codes, reduce="amax")
    has_sh = tw["shgrid"] is not None
    sh = bilinear_t(tw["shadow"], tw["shgrid"], px, py).clamp(0, 1) if has_sh else torch.zeros_like(s)
    return col, lab, nrm, sh, code


def _item_effects(it: dict, item, x, y, fp, tiles):
    """Per (point, item) pair: colour factor (P,), membership (P,) bool, base darkening (P,)."""
    prm = it["prm"][item]
    cls = prm[:, 0].long()
    is_line = (cls == 0) | (cls == 1) | (cls == 4)
    factor = torch.ones_like(x)
    base = torch.ones_like(x)
    member = torch.zeros_like(x, dtype=torch.bool)
    fpc = fp.clamp(min=1e-3)
    li = torch.nonzero(is_line).squeeze(1)
    if li.numel():
        L = it["lines"][item[li]]  # (P, M, 2)
        a, b = L[:, :-1], L[:, 1:]
        ab = b - a
        pt = torch.stack([x[li], y[li]], 1)[:, None]
        ap = pt - a
        tt = ((ap * ab).sum(-1) / ((ab * ab).sum(-1) + 1e-12)).clamp(0, 1)
        dist = (ap - tt[..., None] * ab).norm(dim=-1).min(1).values
        w = prm[li, 2]
        core = ((w / 2 - dist) / fpc[li] + 0.5).clamp(0, 1) * (w / fpc[li]).clamp(max=1)
        halo = (1 - dist / 0.07).clamp(0, 1) * 0.18
        factor[li] = (1 - prm[li, 4] * core) * (1 - halo)
        member[li] = dist < prm[li, 3]
    bi = torch.nonzero(~is_line).squeeze(1)
    if bi.numel():
        q_ = prm[bi]
        c, s = torch.cos(q_[:, 9]), torch.sin(q_[:, 9])
        dx, dy = x[bi] - q_[:, 5], y[bi] - q_[:, 6]
        lu = c * dx + s * dy
        lv = -s * dx + c * dy
        u, v = lu / q_[:, 7], lv / q_[:, 8]
        rho = torch.sqrt(u * u + v * v)
        phi = torch.atan2(v, u)
        q = rho / (1 + q_[:, 10] * torch.cos(2 * phi + q_[:, 12]) + q_[:, 11] * torch.cos(3 * phi + q_[:, 13]))
        inside = q < 1
        member[bi] = inside
        is_pot = q_[:, 0] == 3
        # alligator: Voronoi crack network (distance to the nearest cell boundary) in a darkened patch
        cell = q_[:, 14]
        gu, gv = lu / cell, lv / cell
        iu, iv = gu.floor(), gv.floor()
        d1 = torch.full_like(gu, 9.0)
        d2 = torch.full_like(gu, 9.0)
        for du in (-1.0, 0.0, 1.0):
            for dv in (-1.0, 0.0, 1.0):
                cu, cv = iu + du, iv + dv
                ju = cu + 0.15 + 0.7 * _hash01(cu, cv, q_[:, 15])
                jv = cv + 0.15 + 0.7 * _hash01(cv, cu, q_[:, 15] + 3.0)
                dd = torch.sqrt((gu - ju) ** 2 + (gv - jv) ** 2)
                d2 = torch.where(dd < d1, d1, torch.minimum(d2, dd))
                d1 = torch.minimum(d1, dd)
        edge = 0.5 * (d2 - d1) * cell
        w = q_[:, 2]
        net = ((w / 2 - edge) / fpc[bi] + 0.5).clamp(0, 1) * (w / fpc[bi]).clamp(max=1)
        fade = ((1 - q) / 0.08).clamp(0, 1)
        allig = (1 - q_[:, 4] * net * fade)
        n = value_noise(tiles[3], x[bi], y[bi], 0.03)
        pot = 0.45 + 0.3 * n  # darker, rough, wet-looking interior
        rim = torch.exp(-(((q - 1.0) / 0.06) ** 2)) * 0.15
        factor[bi] = torch.where(is_pot, torch.where(inside, pot, 1 - rim), torch.where(inside, allig, 1.0))
        base[bi] = torch.where(inside & ~is_pot, 0.9 + 0.05 * n, 1.0)
    return factor, member, base


def _object_shade(tw: dict, kind: torch.Tensor, colour: torch.Tensor, local: torch.Tensor, axis: torch.Tensor,
                  hsz: torch.Tensor, tiles):
    """Albedo of box faces from their local hit point: windows, streaks, tyres, glass."""
    k = {n: i for i, n in enumerate(OBJECT_KINDS)}
    # face coordinates: u along the face, v height above the box bottom
    u = torch.where(axis == 0, local[:, 1], local[:, 0])
    v = local[:, 2] + hsz[:, 2]
    col = colour.clone()
    n = value_noise(tiles[1], u * 3.0 + v, v * 3.0, 1.0)
    col = col * (0.92 + 0.16 * n)[:, None]
    bld = (kind == k["building"]) & (axis != 2)
    fu = torch.remainder(u + 100.0, 3.2) / 3.2
    fv = torch.remainder(v - 1.0, 3.2) / 3.2
    win = bld & (fu > 0.25) & (fu < 0.75) & (fv > 0.3) & (fv < 0.8) & (v > 1.5) & (v < 2 * hsz[:, 2] - 1.0)
    glass = torch.tensor([0.16, 0.19, 0.24], device=col.device) * (0.8 + 0.6 * _hash01(
        torch.floor((u + 100.0) / 3.2), torch.floor((v - 1.0) / 3.2), torch.zeros_like(u)))[:, None]
    col = torch.where(win[:, None], glass, col)
    roof = (axis == 2) & ((kind == k["building"]) | (kind == k["wall"]))
    col = torch.where(roof[:, None], col * 0.6, col)
    # crack-like dark streaks on walls and some facades (false-positive bait)
    wall = (kind == k["wall"]) | (kind == k["building"])
    sn = value_noise(tiles[2], u * 0.8, v * 0.25, 1.0)
    streak = wall & ((sn - 0.5).abs() < 0.018) & (axis != 2)
    col = torch.where(streak[:, None], col * 0.35, col)
    # car: dark glass on the cabin sides, bumper line
    # car: dark glass on the cabin sides between a sill and the roof edge, body-coloured roof and pillars
    h2 = 2 * hsz[:, 2]
    pillar = (u.abs() > 0.9 * torch.where(axis == 0, hsz[:, 1], hsz[:, 0]))
    cabin_side = (kind == k["car_cabin"]) & (axis != 2) & (v > 0.1 * h2) & (v < 0.85 * h2) & ~pillar
    col = torch.where(cabin_side[:, None], torch.tensor([0.1, 0.12, 0.15], device=col.device) + 0.0 * col, col)
    # body: darker bumper band at the bottom
    bumper = (kind == k["car_body"]) & (axis != 2) & (v < 0.25 * 2 * hsz[:, 2])
    col = torch.where(bumper[:, None], col * 0.55, col)
    return col


# ---------------------------------------------------------------------------- view


CHUNK_PIXELS = 262144  # rays per chunk: bounds memory on large images


def render_view(world: World, camera: Camera, T_world_cam: np.ndarray, exposure: float = 1.0,
                white_balance: tuple[float, float, float] = (1.0, 1.0, 1.0), noise_seed: int = 0,
                device: str | torch.device = "cpu", threads: int | None = DEFAULT_THREADS) -> RenderOutput:
    """Render one view of ``world`` seen by ``camera`` at pose ``T_world_cam`` (4, 4) camera-to-world."""
    with torch_threads(threads):
        return _render_view(world, camera, T_world_cam, exposure, white_balance, noise_seed, device)


def _render_view(world: World, camera: Camera, T_world_cam: np.ndarray, exposure: float,
                 white_balance: tuple[float, float, float], noise_seed: int, device) -> RenderOutput:
    dev = resolve_device(device)
    tw = world.tensors(dev)
    H, W = camera.height, camera.width
    K = np.asarray(camera.K, np.float64)
    T = np.asarray(T_world_cam, np.float64)
    R, o_np = T[:3, :3], T[:3, 3]
    if "box_corners" not in tw:
        tw["box_corners"] = box_corners(world.boxes) if len(world.boxes) else np.zeros((0, 8, 3))
        sp = world.spheres.astype(np.float64)
        tw["sphere_cubes"] = sp[:, None, :3] + sp[:, None, 3:4] * np.array(
            [[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], float)[None]
    brects = screen_rects(tw["box_corners"], R, o_np, K, W, H, edges=BOX_EDGES)
    srects = screen_rects(tw["sphere_cubes"], R, o_np, K, W, H, edges=BOX_EDGES)
    ground_ref = _ground_reference(world, o_np)
    rgb = np.empty((H * W, 3), np.uint8)
    label = np.empty(H * W, np.uint8)
    depth = np.empty(H * W, np.float32)
    code = np.empty(H * W, np.int64)
    obj = np.empty(H * W, np.int64)
    rows = max(1, CHUNK_PIXELS // W)
    for r0 in range(0, H, rows):
        r1 = min(H, r0 + rows)
        out = _render_rows(world, tw, K, T, W, r0, r1, _clip_rects(brects, r0, r1),
                           _clip_rects(srects, r0, r1), ground_ref, exposure, white_balance, noise_seed)
        sl = slice(r0 * W, r1 * W)
        rgb[sl], label[sl], depth[sl], code[sl], obj[sl] = (x.cpu().numpy() for x in out)
    low = code & (SHADOW_BIT - 1)
    instance = np.where(low < DECOY_ID_OFFSET, low, 0).astype(np.int32)
    return RenderOutput(
        rgb=rgb.reshape(H, W, 3), label=label.reshape(H, W), depth=depth.reshape(H, W),
        instance=instance.reshape(H, W), code=code.astype(np.uint16).reshape(H, W),
        obj=obj.astype(np.int32).reshape(H, W),
    )


def _clip_rects(rects, r0: int, r1: int):
    """Rectangles restricted to rows [r0, r1), rows made relative to r0."""
    out = []
    for k, u0, u1, v0, v1 in rects:
        a, b = max(v0, r0), min(v1, r1)
        if b > a:
            out.append((k, u0, u1, a - r0, b - r0))
    return out


def _ground_reference(world: World, o_np: np.ndarray) -> tuple[float, float, float]:
    """Ground height under the camera and the mean slope (gx, gy) within ±3 m."""
    ox, oy = float(o_np[0]), float(o_np[1])
    e = 3.0
    xs = np.array([ox, ox + e, ox - e, ox, ox])
    ys = np.array([oy, oy, oy, oy + e, oy - e])
    h = world.height_at(xs, ys)
    return float(h[0]), float((h[1] - h[2]) / (2 * e)), float((h[3] - h[4]) / (2 * e))


def _render_rows(world: World, tw: dict, K: np.ndarray, T: np.ndarray, W: int, r0: int,
                 r1: int, brects, srects, ground_ref, exposure: float, white_balance, noise_seed: int):
    """Render image rows [r0, r1): rgb (n, 3) uint8, label (n,) uint8, depth (n,), code (n,), obj (n,)."""
    dev = tw["device"]
    n = (r1 - r0) * W
    pix = pixel_grid(W, r1 - r0, device=dev)
    pix[:, 1] += r0
    _, d = pixel_rays(K, T, pix)  # (n, 3), camera z = 1: the ray parameter λ is the depth
    dx, dy, dz = d.T.contiguous()
    o_np = T[:3, 3]
    o = torch.as_tensor(o_np, dtype=torch.float32, device=dev)
    lam_b, win_b, binfo = intersect_boxes(tw, brects, o, dx, dy, dz, W)
    lam_s, win_s, sinfo = intersect_spheres(tw, srects, o, dx, dy, dz, W)
    lam_o = torch.minimum(lam_b, lam_s)
    lam_g = intersect_ground(world, tw, o_np, dx, dy, dz, ground_ref, limit=lam_o)

    depth = torch.minimum(lam_g, lam_o)
    hit_any = torch.isfinite(depth)
    is_g = hit_any & (lam_g <= depth)
    is_b = hit_any & ~is_g & (lam_b <= depth)
    is_s = hit_any & ~is_g & ~is_b

    col = torch.zeros((n, 3), device=dev)
    nrm = torch.zeros((n, 3), device=dev)
    shadow = torch.zeros(n, device=dev)
    label = torch.full((n,), SKY, dtype=torch.long, device=dev)
    code = torch.zeros(n, dtype=torch.long, device=dev)
    obj = torch.zeros(n, dtype=torch.long, device=dev)
    fx = float(K[0, 0])
    dnorm = d.norm(dim=1)

    gi = torch.nonzero(is_g).squeeze(1)
    if gi.numel():
        lam = lam_g[gi]
        px = o[0] + lam * d[gi, 0]
        py = o[1] + lam * d[gi, 1]
        fp = lam * dnorm[gi] / fx
        c, lab, nr, sh, cd = _ground_shade(world, tw, px, py, fp)
        col[gi], label[gi], nrm[gi], shadow[gi] = c, lab, nr, sh
        code[gi] = cd + torch.where(sh > 0.5, SHADOW_BIT, 0)

    bi = torch.nonzero(is_b).squeeze(1)
    if bi.numel():
        pix, bid, lo, ld, tn, axis = binfo
        w = win_b[bi]
        box = tw["boxes"][bid[w]]
        ax = axis[w]
        ldw = torch.stack([ld[0][w], ld[1][w], ld[2][w]], 1)
        local = lo[w] + tn[w, None] * ldw
        sgn = -torch.sign(ldw.gather(1, ax[:, None]).squeeze(1))
        ln = torch.zeros((w.numel(), 3), device=dev)
        ln.scatter_(1, ax[:, None], sgn[:, None])
        cb, sb = torch.cos(box[:, 6]), torch.sin(box[:, 6])
        nrm[bi] = torch.stack([cb * ln[:, 0] - sb * ln[:, 1], sb * ln[:, 0] + cb * ln[:, 1], ln[:, 2]], 1)
        kind = box[:, 11].long()
        col[bi] = _object_shade(tw, kind, box[:, 7:10], local, ax, box[:, 3:6], tw["tiles"])
        label[bi] = box[:, 10].long()
        obj[bi] = kind + 1

    si = torch.nonzero(is_s).squeeze(1)
    if si.numel():
        pix, sid, lam_pairs = sinfo
        w = win_s[si]
        spr = tw["spheres"][sid[w]]
        hitp = o[None] + lam_s[si, None] * d[si]
        nr = (hitp - spr[:, :3]) / spr[:, 3:4]
        nrm[si] = nr
        leaf = 0.5 * (value_noise(tw["tiles"][2], hitp[:, 0], hitp[:, 2], 0.22)
                      + value_noise(tw["tiles"][3], hitp[:, 1], hitp[:, 2] + 7.0, 0.22))
        col[si] = spr[:, 4:7] * (0.6 + 0.8 * leaf)[:, None]
        label[si] = spr[:, 7].long()
        obj[si] = tw["sphere_kind"][sid[w]] + 1

    # lighting: sky ambient + sun (ground gets cast shadows)
    sun = tw["sun"]
    ndl = (nrm * sun[None]).sum(1).clamp(min=0)
    light = 0.48 + 0.72 * ndl * (1 - 0.85 * shadow)
    col = col * light[:, None]
    # sky gradient and distance haze
    elev = d[:, 2] / dnorm
    hz_c = HORIZON.to(dev)
    sky = hz_c[None] + (ZENITH.to(dev) - hz_c)[None] * (elev * 2.5).clamp(0, 1)[:, None]
    dist = torch.where(hit_any, depth * dnorm, torch.zeros_like(depth))
    haze = (1 - torch.exp(-dist / 380.0))[:, None]
    col = torch.where(hit_any[:, None], col * (1 - haze) + hz_c[None] * haze, sky)
    col = col * exposure * torch.tensor(white_balance, device=dev)[None]
    # mild sensor noise, deterministic per view
    pixid = torch.arange(r0 * W, r1 * W, device=dev, dtype=torch.float32)
    col = col + (_hash01(pixid, pixid * 0.37, float(noise_seed % 1000)) - 0.5)[:, None] * (3.0 / 255)
    rgb = (col.clamp(0, 1) * 255 + 0.5).to(torch.uint8)

    depth_out = torch.where(hit_any, depth, torch.zeros_like(depth))
    return rgb, label.to(torch.uint8), depth_out, code, obj


__all__ = ["RenderOutput", "render_view", "SHADOW_BIT", "BUILDING", "ROAD", "TERRAIN"]
