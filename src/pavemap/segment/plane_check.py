"""Road pixels that do not lie on the road: the plane-parallax check of a segmenter's road mask.

A Cityscapes network calls the lower half of a vehicle it does not know, a kerb and a sidewalk "road" when
they look like asphalt. Geometry tells them apart: a point on the road plane maps from one view to another
by the plane's homography, a point 30 cm above it lands tens of pixels off at a few metres' baseline. So for
each posed view, two partner views of the same camera (the nearest frame before and after it at least
``min_baseline_m`` away) are warped onto it through the road plane ``camera_height`` below the camera;
road-labelled pixels whose colour disagrees in every partner that sees them are relabelled ``above_road``
(a movable class: no stage uses it as ground, and the road filter does not count it as road).

A uniform surface (a vehicle's flat panel, a plain sidewalk) agrees with itself under any warp, so only its
edges disagree: the edges are spread around by a density rule (``window`` of the image width, ``density``), and
over a colour-uniform region (Felzenszwalb's graph segmentation) whose off-plane pixels outnumber its textured
agreeing ones (a uniform pixel agrees under any warp and says nothing) and cover ``region_min_off_share`` of it;
a region with more than ``region_max_share`` of the view's road is the road itself and stays (real asphalt is
smooth at this resolution: its scattered disagreements from shadows and pose noise are not a panel's edges).
A vehicle moving with the camera disagrees too: it is not road either. A view whose partners do not register on
the road (the disagreement on its best-agreeing quarter of the road above ``max_noise_diff``: poses or the height
off, an exposure jump) is left as it was, and so is a view where more than ``max_flagged`` of the road would go:
that is a check gone wrong, not a road full of cars (there only the road above the horizon goes).

Above the horizon no road lies: road-labelled pixels whose ray rises above the highest road the drive's own path
shows (the road under every camera centre within ``horizon_radius_m``, so a climb the car drives is kept) by more
than ``horizon_margin_deg`` are relabelled too, in the checked views (a uniform sky or roof agrees under any warp).
Road beyond the path's end that climbs more steeply is lost above the margin; it lies off the mapped corridor.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import torch
from torch.nn import functional as F  # noqa: N812

from pavemap.geometry.triangulate import plane_homography
from pavemap.segment.relabel_report import RelabelReport
from pavemap.types import Camera, Sequence, View

log = logging.getLogger(__name__)

Z_UP = np.array([0.0, 0.0, 1.0])


@dataclass(frozen=True)
class PlaneCheckConfig:
    """Settings of :func:`plane_check_sequence` (chosen on the synthetic presets, `bench/segment_bench.py`)."""

    max_width: int = 640  # working resolution: images wider than this are resized down
    min_baseline_m: float = 1.5  # a partner view is at least this far from the view ...
    max_baseline_m: float = 15.0  # ... and at most this far
    blur_px: float = 1.0  # Gaussian sigma at the working resolution (resampling noise)
    tolerance_px: int = 2  # a colour found this near in the partner agrees (poses and height a little off)
    diff_min: float = 0.08  # colour disagreement (0..1, mean over channels) that counts as "off the plane" ...
    noise_quantile: float = 0.1  # the pair's noise: this quantile of the disagreement on static ground ...
    diff_noise_k: float = 4.0  # ... times this is the threshold, where larger than diff_min
    max_noise_diff: float = 0.03  # a pair whose noise is above this does not register on the plane: not used
    window: float = 0.04  # density rule: box window, share of the image width ...
    density: float = 0.15  # ... in which this share of the pixels disagree
    max_flagged: float = 0.5  # a view losing more of its road than this is left unchanged
    regions: bool = True  # spread the verdict over colour-uniform regions (felzenszwalb) ...
    region_scale: float = 200.0  # ... of this scale
    region_ratio: float = 2.0  # ... whose off-plane pixels outnumber their textured on-plane ones this many times
    region_min_px: int = 30
    region_min_off_share: float = 0.1  # ... and cover at least this share of the region
    region_max_share: float = 0.3  # a region with more of the view's road than this is the road itself: kept
    texture_min: float = 0.04  # gradient (0..1 per pixel) above which an agreeing pixel is evidence of the plane
    horizon: bool = True  # no road above the path's horizon (below)
    horizon_margin_deg: float = 1.0  # road rising this far above the path's highest road is not road (pose pitch)
    horizon_radius_m: float = 200.0  # the path's road this near a view bounds where its road can rise


@dataclass
class PlaneCheckReport(RelabelReport):
    """What :func:`plane_check_sequence` did, for the console and the stamp (``skipped``: up to 10
    "camera/frame: why")."""

    checked: int = 0
    no_partner: int = 0
    not_registered: int = 0
    too_much: int = 0

    def describe(self) -> str:
        text = (f"plane check: {self.checked}/{self.views} views checked, {100 * self.share:.1f} % of their road "
                "pixels are off the road plane (relabelled above_road)")
        left = [f"{n} {why}" for n, why in ((self.no_partner, "without a partner view"),
                                             (self.not_registered, "whose partners do not register on the road"),
                                             (self.too_much, "that would lose most of their road (there only the road "
                                                             "above the horizon went)")) if n]
        return text + (f"; left unchanged: {', '.join(left)}" if left else "")


def _blur(img: torch.Tensor, sigma: float) -> torch.Tensor:
    """(C, H, W) float32 -> the same, Gaussian-blurred (separable, reflect-free zero padding)."""
    r = max(1, int(round(2 * sigma)))
    t = torch.arange(-r, r + 1, dtype=torch.float32)
    g = torch.exp(-(t**2) / (2 * sigma**2))
    g = g / g.sum()
    c = img.shape[0]
    x = F.conv2d(img[None], g.view(1, 1, 1, -1).repeat(c, 1, 1, 1), padding=(0, r), groups=c)
    return F.conv2d(x, g.view(1, 1, -1, 1).repeat(c, 1, 1, 1), padding=(r, 0), groups=c)[0]


def plane_in_front(K_i: np.ndarray, T_i: np.ndarray, normal: np.ndarray, offset: float,
                   size_i: tuple[int, int]) -> torch.Tensor:
    """(Hi, Wi) bool: the pixels of view i whose ray meets the plane ``normal . X = offset`` in front of the
    camera (below the horizon of a road plane)."""
    h, w = size_i
    n_i = T_i[:3, :3].T @ normal
    d_i = offset - float(normal @ T_i[:3, 3])
    a = np.linalg.inv(K_i).T @ n_i  # n_i . K^-1 (u, v, 1) = a . (u, v, 1)
    v, u = torch.meshgrid(torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64), indexing="ij")
    return (a[0] * u + a[1] * v + a[2]) * d_i > 0


def above_path_horizon(cam: Camera, T_i: np.ndarray, centres: np.ndarray, height: float,
                       cfg: PlaneCheckConfig = PlaneCheckConfig()) -> np.ndarray:
    """(H, W) bool at ``cam``'s size: the pixels of view i whose ray rises above the highest road point of the
    drive's path seen from it (the road ``height`` under each of ``centres`` (N, 3) within ``horizon_radius_m``,
    and the flat horizon) by more than ``horizon_margin_deg``. World z is up."""
    c = T_i[:3, 3]
    dist = np.linalg.norm(centres[:, :2] - c[:2], axis=1)
    near = (dist >= 1.0) & (dist <= cfg.horizon_radius_m)
    rise = np.arctan2(centres[near, 2] - height - c[2], dist[near])
    limit = np.radians(cfg.horizon_margin_deg) + float(rise.max(initial=0.0))  # the flat horizon at least
    M = (T_i[:3, :3] @ np.linalg.inv(cam.K)).astype(np.float32)  # world ray = M (u, v, 1): linear in u and v
    u = np.arange(cam.width, dtype=np.float32)[None, :]
    v = np.arange(cam.height, dtype=np.float32)[:, None]
    x, y, z = (M[k, 0] * u + M[k, 1] * v + M[k, 2] for k in range(3))
    return z > np.float32(np.sin(limit)) * np.sqrt(x * x + y * y + z * z)


def warp_through_plane(img_j: torch.Tensor, H_ij: np.ndarray, size_i: tuple[int, int]) -> tuple[torch.Tensor,
                                                                                                 torch.Tensor]:
    """View j's image seen from view i through a plane: ``H_ij`` (3, 3), unnormalised
    (:func:`~pavemap.geometry.triangulate.plane_homography` ``normalise=False``), maps pixels of i to pixels of j.

    img_j (C, Hj, Wj) float32; size_i (Hi, Wi) -> warped (C, Hi, Wi) float32, valid (Hi, Wi) bool (the plane
    point on the same side of both cameras and inside j's image; AND it with :func:`plane_in_front`)."""
    h, w = size_i
    v, u = torch.meshgrid(torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64), indexing="ij")
    p = torch.stack([u, v, torch.ones_like(u)], -1) @ torch.as_tensor(H_ij, dtype=torch.float64).T
    z = p[..., 2]
    zs = torch.where(z.abs() < 1e-9, torch.full_like(z, 1e-9), z)
    uj, vj = p[..., 0] / zs, p[..., 1] / zs
    hj, wj = img_j.shape[1:]
    valid = (z > 0) & (uj >= 0) & (uj <= wj - 1) & (vj >= 0) & (vj <= hj - 1)
    grid = torch.stack([(uj + 0.5) / wj * 2 - 1, (vj + 0.5) / hj * 2 - 1], -1).clamp(-2, 2).float()[None]
    out = F.grid_sample(img_j[None], grid, mode="bilinear", align_corners=False, padding_mode="border")[0]
    return out, valid


def _tolerant_diff(img: torch.Tensor, warped: torch.Tensor, r: int) -> torch.Tensor:
    """(H, W): how far each pixel's colour lies outside the range the warped image takes within ``r`` pixels of it
    (img, warped (3, H, W)); a road line the poses put 1-2 px off is not a disagreement, a car's edge tens off is."""
    if r <= 0:
        return (img - warped).abs().mean(0)
    k = 2 * r + 1
    hi = F.max_pool2d(warped[None], k, 1, r)[0]
    lo = -F.max_pool2d(-warped[None], k, 1, r)[0]
    return ((img - hi).clamp_min(0) + (lo - img).clamp_min(0)).mean(0)


def _anchored(off: torch.Tensor, anchor: torch.Tensor) -> torch.Tensor:
    """The 8-connected regions of ``off`` (H, W) bool that touch ``anchor`` (H, W) bool (grown by a pixel)."""
    from scipy import ndimage

    lab, n = ndimage.label(off.numpy(), structure=np.ones((3, 3), bool))
    if n == 0:
        return off
    grown = F.max_pool2d(anchor.float()[None, None], 3, 1, 1)[0, 0].numpy() > 0
    keep = np.zeros(n + 1, bool)
    keep[np.unique(lab[grown & (lab > 0)])] = True
    keep[0] = False
    return torch.from_numpy(keep[lab])


def off_plane_mask(img_i: torch.Tensor, partners: list[tuple[torch.Tensor, np.ndarray]], road: torch.Tensor,
                   reference: torch.Tensor, cfg: PlaneCheckConfig = PlaneCheckConfig(),
                   anchor: torch.Tensor | None = None) -> tuple[torch.Tensor | None, str]:
    """Road pixels of view i that are off the plane.

    img_i (3, H, W) float32 0..1 (blurred); partners: (img_j (4, Hj, Wj): blurred RGB and 1 where j sees the
    scene, 0 on its own vehicle (the bonnet hides the road behind it), H_ij (3, 3) unnormalised);
    road (H, W) bool: the pixels to judge; reference (H, W) bool: where the pair's registration and noise are
    read (every static pixel below the horizon: a side camera's "road" may be all vehicle); anchor (H, W) bool:
    the pixels labelled something other than road (not the ego vehicle): an off-plane region is kept only where it
    touches one (a vehicle's foot joins the vehicle; a patch amid the road is a pose or height error there).
    Returns ((H, W) bool, "") or (None, why) when no partner registers on the plane."""
    off = torch.ones_like(road)
    seen = torch.zeros_like(road)
    agrees = torch.zeros_like(road)
    for img_j, H in partners:
        warped, valid = warp_through_plane(img_j, H, tuple(road.shape))
        valid &= warped[3] > 0.99
        warped = warped[:3]
        m = reference & valid
        if int(m.sum()) < 50:
            continue
        # an exposure change between the two frames is a gain per channel, read where the two already agree
        # best (not over all static ground: much of it may be a wall or a vehicle that is off the plane)
        d0 = (img_i - warped).abs().mean(0)
        agree = m & (d0 <= torch.quantile(d0[m][:: max(1, int(m.sum()) // 200000)], 0.25))
        gain = (img_i[:, agree].median(1).values / warped[:, agree].median(1).values.clamp_min(1e-3)).clamp(0.5, 2.0)
        diff = _tolerant_diff(img_i, warped * gain[:, None, None], cfg.tolerance_px)
        # much below the horizon stands off the plane: the pair's noise is read on its best-agreeing tenth
        low = float(torch.quantile(diff[m][:: max(1, int(m.sum()) // 200000)], cfg.noise_quantile))
        if low > cfg.max_noise_diff:
            continue
        thr = max(cfg.diff_min, cfg.diff_noise_k * low)
        off &= ~valid | (diff > thr)
        agrees |= valid & (diff <= thr)
        seen |= valid
    if not bool(seen.any()):
        return None, "not_registered"
    off &= seen & road  # a road nobody else sees (or no road) stays as labelled
    o = off.float()[None, None]
    o = F.max_pool2d(-F.max_pool2d(-o, 3, 1, 1), 3, 1, 1)  # opening: single-pixel noise out
    k = max(3, int(round(cfg.window * road.shape[1])) | 1)
    dens = F.avg_pool2d(o, k, 1, k // 2, count_include_pad=False)[0, 0]
    off = (dens > cfg.density) & road
    if cfg.regions:
        off |= _region_verdict(img_i, o[0, 0] > 0, agrees & road, road, cfg)
    return (off if anchor is None else _anchored(off, anchor)), ""


def _region_verdict(img: torch.Tensor, off: torch.Tensor, agrees: torch.Tensor, road: torch.Tensor,
                    cfg: PlaneCheckConfig) -> torch.Tensor:
    """(H, W) bool: the road of every colour-uniform region of ``img`` (3, H, W) whose off-plane pixels ``off``
    outnumber its textured agreeing ones (``agrees`` where the image has texture: a uniform pixel agrees under
    any warp and says nothing) ``region_ratio`` times: a flat panel or a plain sidewalk, whose parallax shows only
    at its edges."""
    from skimage.segmentation import felzenszwalb

    gx = (img[:, :, 2:] - img[:, :, :-2]).abs().mean(0)
    gy = (img[:, 2:, :] - img[:, :-2, :]).abs().mean(0)
    grad = torch.zeros(img.shape[1:])
    grad[:, 1:-1] = gx
    grad[1:-1, :] = torch.maximum(grad[1:-1, :], gy)
    on = agrees & ~off & (grad > cfg.texture_min)
    reg = felzenszwalb(img.permute(1, 2, 0).numpy(), scale=cfg.region_scale, sigma=0.5, min_size=cfg.region_min_px)
    reg_t = torch.from_numpy(reg.astype(np.int64))
    n = int(reg.max()) + 1
    n_off = torch.bincount(reg_t[off & road], minlength=n)
    n_on = torch.bincount(reg_t[on & road], minlength=n)
    n_road = torch.bincount(reg_t[road], minlength=n)
    bad = ((n_off >= cfg.region_min_px) & (n_off > cfg.region_ratio * n_on)
           & (n_off >= cfg.region_min_off_share * n_road) & (n_road <= cfg.region_max_share * int(road.sum())))
    return bad[reg_t] & road


def _partners(views: list[tuple[int, View]], i: int, cfg: PlaneCheckConfig) -> list[int]:
    """Indices of the nearest view before and after ``i`` (one camera's, in frame order) at a usable baseline."""
    c = views[i][1].T_world_cam[:3, 3]
    out = []
    for step in (-1, 1):
        j = i + step
        while 0 <= j < len(views):
            d = float(np.linalg.norm(views[j][1].T_world_cam[:3, 3] - c))
            if d > cfg.max_baseline_m:
                break
            if d >= cfg.min_baseline_m:
                out.append(j)
                break
            j += step
    return out


def _working(cam: Camera, cfg: PlaneCheckConfig) -> tuple[float, Camera]:
    scale = min(1.0, cfg.max_width / cam.width)
    return scale, cam.scaled(scale) if scale < 1.0 else cam


def _image(seq: Sequence, v: View, size: tuple[int, int], ego_ids: np.ndarray, cfg: PlaneCheckConfig
           ) -> torch.Tensor:
    """(4, h, w) float32 at the working ``size`` (w, h): the blurred RGB 0..1 and 1 off the ego vehicle."""
    from PIL import Image

    from pavemap.io.sequence import load_rgb, load_semantics

    img = load_rgb(seq.path(v.image))
    if img.shape[1] != size[0]:
        img = np.asarray(Image.fromarray(img).resize(size, Image.BILINEAR))
    rgb = _blur(torch.from_numpy(np.array(img)).permute(2, 0, 1).float() / 255.0, cfg.blur_px)  # a copy: writable
    scene = _at(torch.from_numpy(~np.isin(load_semantics(seq.path(v.semantics)), ego_ids)), rgb.shape[1:])
    return torch.cat([rgb, scene.float()[None]])


def _at(mask: torch.Tensor, shape: tuple[int, int]) -> torch.Tensor:
    """(h, w) bool resized (nearest) to ``shape``."""
    if tuple(mask.shape) == tuple(shape):
        return mask
    return F.interpolate(mask.float()[None, None], size=tuple(shape), mode="nearest")[0, 0] > 0.5


def _check_view(seq: Sequence, cam: Camera, views: list[tuple[int, View]], i: int, cache: dict[int, torch.Tensor],
                road_ids: np.ndarray, skip_ids: np.ndarray, ego_ids: np.ndarray, height: float,
                centres: np.ndarray, cfg: PlaneCheckConfig
                ) -> tuple[np.ndarray | None, np.ndarray | None, str]:
    """(labels (H, W) uint8, road to relabel (H, W) bool, why) for ``views[i]``; why: "" or a
    :class:`PlaneCheckReport` counter: labels None when the view is left as it was, or ``too_much`` when only its
    road above the horizon goes (the parallax would take most of its road: a check gone wrong; the partners
    registering on the road vouch for the pose's pitch). ``centres`` (N, 3): the camera's centres along the drive."""
    from pavemap.io.sequence import load_semantics

    partners = _partners(views, i, cfg)
    if not partners:
        return None, None, "no_partner"
    _, wcam = _working(cam, cfg)
    size = (wcam.width, wcam.height)
    for j in [i, *partners]:
        if j not in cache:
            cache[j] = _image(seq, views[j][1], size, ego_ids, cfg)
    T_i = views[i][1].T_world_cam
    offset = float(Z_UP @ T_i[:3, 3]) - height
    pairs = [(cache[j], plane_homography(wcam.K, T_i, wcam.K, views[j][1].T_world_cam, Z_UP, offset, False))
             for j in partners]
    labels = load_semantics(seq.path(views[i][1].semantics))
    road_full = np.isin(labels, road_ids)
    below = plane_in_front(wcam.K, T_i, Z_UP, offset, (wcam.height, wcam.width))  # above the horizon: no plane
    road, static = (_at(torch.from_numpy(m), below.shape) & below for m in (road_full, ~np.isin(labels, skip_ids)))
    anchor = _at(torch.from_numpy(~road_full & ~np.isin(labels, ego_ids)), below.shape)
    off, why = off_plane_mask(cache[i][:3], pairs, road, static, cfg, anchor)
    if off is None:
        return None, None, why
    off_np = _at(off, road_full.shape).numpy() & road_full
    sky = np.zeros_like(road_full)
    if cfg.horizon and road_full.shape == (cam.height, cam.width):
        sky = road_full & above_path_horizon(cam, T_i, centres, height, cfg)
    if (off_np & ~sky).sum() > cfg.max_flagged * max(int(road_full.sum()), 1):
        return labels, sky, "too_much"
    return labels, off_np | sky, ""


def plane_check_sequence(seq: Sequence, camera_height: float | None = None,
                         cfg: PlaneCheckConfig = PlaneCheckConfig()) -> PlaneCheckReport:
    """Relabel the road pixels of every posed view's semantics that lie off the road plane (module docstring).

    ``camera_height``: the mount's height over the road (m); None: each camera's ``height_m``; a camera with
    neither is not checked. The label PNGs are rewritten in place (they are the segmenter's, just written)."""
    from pavemap.segment import _save_labels

    rep = PlaneCheckReport()
    above = next((c.id for c in seq.classes if c.name == "above_road"), None)
    road_ids = np.array([c.id for c in seq.classes if c.road], dtype=np.int64)
    skip_ids = np.array([c.id for c in seq.classes if c.movable or c.sky], dtype=np.int64)
    ego_ids = np.array([c.id for c in seq.classes if c.name == "ego"], dtype=np.int64)
    for name, cam in seq.cameras.items():
        views = [(f.index, f.views[name]) for f in seq.frames if name in f.views and f.views[name].semantics]
        rep.views += len(views)
        height = camera_height if camera_height is not None else cam.height_m
        if above is None or height is None or not len(road_ids):
            rep.skipped.append(f"{name}: " + ("no above_road class in the label table" if above is None
                                              else "no camera height known"))
            continue
        cache: dict[int, torch.Tensor] = {}
        centres = np.array([w.T_world_cam[:3, 3] for _, w in views]).reshape(-1, 3)
        for i, (frame, v) in enumerate(views):
            for k in [k for k in cache if k < i - 16]:
                del cache[k]  # partners are near frames: an image far behind is not needed again
            labels, off, why = _check_view(seq, cam, views, i, cache, road_ids, skip_ids, ego_ids, float(height),
                                           centres, cfg)
            if why:
                setattr(rep, why, getattr(rep, why) + 1)
                if len(rep.skipped) < 10:
                    rep.skipped.append(f"{name}/{frame}: {why.replace('_', ' ')}")
            if labels is None or off is None:
                continue
            rep.checked += int(not why)
            rep.road_px += int(np.isin(labels, road_ids).sum())
            rep.relabelled_px += int(off.sum())
            if off.any():
                _save_labels(seq.path(v.semantics), np.where(off, np.uint8(above), labels).astype(np.uint8))
    return rep
