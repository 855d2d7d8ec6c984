"""Matplotlib figures (Agg, headless): the paper's Figure 11 layout, a Figure 13-style sweep of
the confidence threshold, and per-frame detection overlays.

Every function writes one PNG atomically and returns its path.
"""

from __future__ import annotations

import os
from collections import Counter
from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # headless: no display on servers / CI

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.collections import PatchCollection  # noqa: E402
from matplotlib.patches import PathPatch, Rectangle  # noqa: E402
from matplotlib.path import Path as MplPath  # noqa: E402

from pavemap.export.geojson import _polygons  # noqa: E402
from pavemap.export.geotiff import check_grid  # noqa: E402
from pavemap.geometry.grid import GridSpec  # noqa: E402
from pavemap.io.atomic import atomic_path  # noqa: E402
from pavemap.palette import DEFECT_HEX, colour_labels
from pavemap.types import DEFECT_CODES, DEFECT_NAMES, DefectInstance  # noqa: E402

# the paper's Figure 11 colours: D00 green, D10 yellow, D20 orange, D40 red
CLASS_COLOURS: dict[str, str] = DEFECT_HEX
# urgency by the maintenance policy (pavemap.maintain.policy.PRIORITIES), most urgent first
PRIORITY_COLOURS: dict[str, str] = {"repair now": "#c0392b", "schedule": "#e67e22", "monitor": "#7f8c8d",
                                    "unassessed": "#bdc3c7"}
PRIORITIES = ("repair now", "schedule", "monitor")
# metrics shown first in the statistics panel, when present (paper names, SPEC §4)
KEY_METRICS = ("filter_rate", "orp", "msr", "coverage", "obs_per_vertex", "severity", "avg_distance_m",
               "precision", "recall", "f1", "loc_error_m", "total_s")


def save_figure(fig: plt.Figure, path: str | os.PathLike, dpi: int = 110, tight: bool = True) -> Path:
    """Save ``fig`` as PNG atomically and close it (``tight`` costs a second render)."""
    try:
        with atomic_path(path) as tmp:
            fig.savefig(tmp, format="png", dpi=dpi, bbox_inches="tight" if tight else None, facecolor="white",
                        pil_kwargs={"compress_level": 4})
    finally:
        plt.close(fig)
    return Path(path)


def grid_extent(grid: GridSpec) -> list[float]:
    """imshow extent [xmin, xmax, ymin, ymax] (cell edges) of a grid whose rows go +y."""
    x0, y0, res, H, W = check_grid(grid)
    return [x0 - res / 2, x0 + (W - 1) * res + res / 2, y0 - res / 2, y0 + (H - 1) * res + res / 2]


def geometry_path(geom: object) -> MplPath | None:
    """A compound matplotlib path of a shapely (Multi)Polygon, holes included."""
    verts, codes = [], []
    for p in _polygons(geom):
        for ring in (p.exterior, *p.interiors):
            c = np.asarray(ring.coords, dtype=np.float64)[:, :2]
            if len(c) < 3:
                continue
            verts.append(c)
            k = np.full(len(c), MplPath.LINETO, dtype=np.uint8)
            k[0] = MplPath.MOVETO
            k[-1] = MplPath.CLOSEPOLY
            codes.append(k)
    if not verts:
        return None
    return MplPath(np.vstack(verts), np.concatenate(codes))


def draw_instances(ax: plt.Axes, instances: list[DefectInstance], alpha: float = 0.55, lw: float = 1.2,
                   colour_by: str = "class") -> None:
    """Filled defect polygons coloured by class (or priority) with a dark outline."""
    patches, faces = [], []
    for inst in instances:
        path = geometry_path(inst.polygon)
        if path is None:
            continue
        patches.append(PathPatch(path))
        faces.append(CLASS_COLOURS[inst.code] if colour_by == "class" else PRIORITY_COLOURS.get(inst.priority, "k"))
    if patches:
        ax.add_collection(PatchCollection(patches, facecolors=faces, edgecolors="black", linewidths=lw,
                                          alpha=alpha, zorder=3))


def flatten_metrics(metrics: dict | None, prefix: str = "") -> dict[str, float | int | str]:
    """Nested metric dicts -> {"a.b": scalar}; lists and arrays are skipped."""
    out: dict[str, float | int | str] = {}
    for k, v in (metrics or {}).items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            out.update(flatten_metrics(v, key + "."))
        elif isinstance(v, (bool, np.bool_)):
            out[key] = str(bool(v))
        elif isinstance(v, (int, float, np.integer, np.floating)):
            out[key] = v.item() if hasattr(v, "item") else v
        elif isinstance(v, str) and len(v) < 40:
            out[key] = v
    return out


def format_value(v: object) -> str:
    if isinstance(v, float):
        if not np.isfinite(v):
            return "–"
        a = abs(v)
        return f"{v:.3g}" if (a < 0.01 and a != 0) or a >= 1e4 else f"{v:.3f}".rstrip("0").rstrip(".")
    return str(v)


# headline metrics: (group title, prefixes tried in order, leaf names in display order)
HEADLINE_GROUPS: tuple[tuple[str, tuple[str, ...], tuple[str, ...]], ...] = (
    ("paper metrics", ("", "paper."), ("filter_rate", "on_road_precision", "orp", "msr", "coverage",
                                        "obs_per_vertex", "mean_severity", "severity", "avg_distance_m",
                                        "total_detections", "mapped_detections")),
    ("evaluation", ("evaluation.", "eval."), ("precision", "recall", "f1", "median_error_m", "loc_error_m",
                                              "class_accuracy", "matched", "predicted", "truth")),
    ("road mesh", ("mesh.",), ("psnr", "sem_acc", "height_rmse")),
    ("seconds", ("seconds.", "timing."), ()),
)


def headline_metrics(metrics: dict | None) -> list[tuple[str, list[tuple[str, str]]]]:
    """The metrics a reader looks at first, grouped: [(group, [(name, value), ...]), ...].

    Groups: the paper's statistics (SPEC §4), the evaluation against ground truth, the mesh quality
    and the per-stage seconds (all leaves of ``seconds``/``timing``). Deeper entries (per class,
    baselines, histories) are left for the full table.
    """
    flat = flatten_metrics(metrics)
    out = []
    for title, prefixes, leaves in HEADLINE_GROUPS:
        rows: list[tuple[str, str]] = []
        if leaves:
            for leaf in leaves:
                key = next((p + leaf for p in prefixes if p + leaf in flat), None)
                if key is not None:
                    rows.append((leaf, format_value(flat[key])))
        else:
            for p in prefixes:
                rows += [(k[len(p):], format_value(v)) for k, v in flat.items()
                         if k.startswith(p) and "." not in k[len(p):]]
                if rows:
                    break
        if rows:
            out.append((title, rows))
    return out


def key_metric_lines(metrics: dict | None, limit: int = 12) -> list[tuple[str, str]]:
    """(name, value) pairs for the statistics panel: the headline metrics, else the first entries."""
    lines = [(f"{name}" if title != "seconds" else f"{name} s", v)
             for title, rows in headline_metrics(metrics) for name, v in rows]
    if not lines:
        lines = [(k, format_value(v)) for k, v in flatten_metrics(metrics).items()]
    return lines[:limit]


def fig_bev_overview(path: str | os.PathLike, bev_rgb: np.ndarray | None, bev_semantic: np.ndarray | None,
                     mesh_grid: GridSpec | None, instances: list[DefectInstance], metrics: dict | None = None,
                     prob_map: np.ndarray | None = None, grid: GridSpec | None = None, title: str = "") -> Path:
    """The paper's Figure 11: (a) BEV RGB, (b) BEV semantics, (c) defect overlay, (d) statistics.

    ``bev_rgb``/``bev_semantic`` (ny, nx, 3) uint8 on ``mesh_grid``; ``prob_map`` (H, W) on ``grid``.
    """
    ext = grid_extent(mesh_grid) if mesh_grid is not None else (grid_extent(grid) if grid is not None else None)
    aspect = (ext[3] - ext[2]) / max(ext[1] - ext[0], 1e-9) if ext is not None else 1.0
    if aspect < 0.55:
        # a long road strip: maps stacked full width, statistics underneath
        map_h = float(np.clip(14.0 * aspect, 1.6, 6.0))
        fig = plt.figure(figsize=(15, 3 * (map_h + 0.9) + 4.2))
        gs = fig.add_gridspec(4, 2, height_ratios=[map_h, map_h, map_h, 3.6], hspace=0.45, wspace=0.15)
        slots = (gs[0, :], gs[1, :], gs[2, :], gs[3, :])
        stats_sub = (1, 2)
    else:
        map_h = float(np.clip(7.0 * aspect, 4.0, 8.0))
        fig = plt.figure(figsize=(15, 2 * map_h + 1.5))
        gs = fig.add_gridspec(2, 2, hspace=0.18, wspace=0.12)
        slots = (gs[0, 0], gs[0, 1], gs[1, 0], gs[1, 1])
        stats_sub = (2, 1)

    def shrink(img: np.ndarray | None, limit: int = 1100) -> np.ndarray | None:
        # a panel is < 1000 px wide at this dpi: decimating first makes Agg's resampling cheap
        if img is None:
            return None
        step = int(np.ceil(max(img.shape[:2]) / limit))
        return img[::step, ::step] if step > 1 else img

    bev_rgb, bev_semantic = shrink(bev_rgb), shrink(bev_semantic)
    if prob_map is not None:
        prob_map = shrink(np.asarray(prob_map))

    def bev_panel(ax: plt.Axes, img: np.ndarray | None, label: str) -> None:
        if img is not None and ext is not None:
            ax.imshow(img, origin="lower", extent=ext, interpolation="nearest")
        else:
            ax.text(0.5, 0.5, "not available", ha="center", va="center", transform=ax.transAxes)
        ax.set_title(label)
        ax.set_xlabel("x (m)")
        ax.set_ylabel("y (m)")
        ax.set_aspect("equal")

    bev_panel(fig.add_subplot(slots[0]), bev_rgb, "(a) BEV RGB")
    bev_panel(fig.add_subplot(slots[1]), bev_semantic, "(b) BEV semantics")
    ax = fig.add_subplot(slots[2])
    if bev_rgb is not None and ext is not None:
        # faded road so the defect colours stand out; cells off the mesh (black) become white
        faded = (bev_rgb.astype(np.float32) * 0.55 + 255 * 0.45).astype(np.uint8)
        faded[np.all(bev_rgb == 0, axis=-1)] = 255
        ax.imshow(faded, origin="lower", extent=ext, interpolation="nearest")
    if prob_map is not None and grid is not None:
        pm = np.ma.masked_less(np.asarray(prob_map, dtype=np.float32), 0.02)
        ax.imshow(pm, origin="lower", extent=grid_extent(grid), cmap="magma_r", vmin=0, vmax=1, alpha=0.6,
                  interpolation="nearest")
    draw_instances(ax, instances)
    if ext is not None:
        ax.set_xlim(ext[0], ext[1])
        ax.set_ylim(ext[2], ext[3])
    handles = [Rectangle((0, 0), 1, 1, fc=CLASS_COLOURS[c], ec="k") for c in DEFECT_CODES]
    ax.legend(handles, [f"{c} {DEFECT_NAMES[c]}" for c in DEFECT_CODES], loc="upper right", fontsize=8,
              framealpha=0.9)
    ax.set_title(f"(c) defects ({len(instances)} instances)")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_aspect("equal")
    if not instances:
        ax.text(0.5, 0.5, "no defects mapped", ha="center", va="center", transform=ax.transAxes, fontsize=14,
                bbox={"fc": "white", "ec": "0.5"})

    if stats_sub == (2, 1):
        sub = slots[3].subgridspec(2, 1, height_ratios=[1, 1.1], hspace=0.35)
    else:
        sub = slots[3].subgridspec(1, 2, width_ratios=[1, 1.3], wspace=0.1)
    axb = fig.add_subplot(sub[0])
    counts = {p: Counter(i.code for i in instances if i.priority == p) for p in PRIORITIES}
    bottom = np.zeros(len(DEFECT_CODES))
    for p in PRIORITIES:
        vals = np.array([counts[p][c] for c in DEFECT_CODES], dtype=float)
        axb.bar(DEFECT_CODES, vals, bottom=bottom, color=PRIORITY_COLOURS[p],
                edgecolor=[CLASS_COLOURS[c] for c in DEFECT_CODES], linewidth=2.5)
        bottom += vals
    for t, c in zip(axb.get_xticklabels(), DEFECT_CODES, strict=False):
        t.set_bbox({"fc": CLASS_COLOURS[c], "ec": "none", "alpha": 0.8, "pad": 2})
    axb.set_ylabel("instances")
    axb.set_title("(d) statistics: instances per class and priority")
    axb.legend([Rectangle((0, 0), 1, 1, fc=PRIORITY_COLOURS[p]) for p in PRIORITIES], PRIORITIES, fontsize=8)
    axb.set_ylim(0, max(1.0, float(bottom.max()) * 1.25))
    axb.yaxis.get_major_locator().set_params(integer=True)
    axt = fig.add_subplot(sub[1])
    axt.axis("off")
    area = sum(float(i.area_m2) for i in instances)
    length = sum(float(i.length_m) for i in instances)
    lines = [("defects", str(len(instances))), ("total area", f"{area:.2f} m²"),
             ("total length", f"{length:.1f} m")]
    lines += [(p, str(sum(counts[p].values()))) for p in PRIORITIES]
    lines += key_metric_lines(metrics, limit=16)
    half = (len(lines) + 1) // 2
    for col, chunk in enumerate((lines[:half], lines[half:])):
        txt = "\n".join(f"{k:<21s} {v}" for k, v in chunk)
        axt.text(0.0 + 0.52 * col, 1.0, txt, va="top", ha="left", family="monospace", fontsize=9,
                 transform=axt.transAxes)
    if title:
        fig.suptitle(title, fontsize=14, y=0.995)
    fig.subplots_adjust(left=0.05, right=0.98, top=0.96 if title else 0.98, bottom=0.04)
    return save_figure(fig, path, tight=False)


def fig_threshold_sweep(path: str | os.PathLike, rows: list[dict], x_key: str = "tau_conf",
                        keys: list[str] | None = None) -> Path:
    """Figure 13-style sweep: each metric against the confidence threshold, one small panel each.

    ``rows``: [{"tau_conf": 0.05, "msr": .., "f1": .., ...}, ...]; nested dicts are flattened.
    """
    flat = [flatten_metrics(r) for r in rows]
    flat = [r for r in flat if isinstance(r.get(x_key), (int, float))]
    if not flat:
        raise ValueError(f"threshold sweep: no rows with a numeric {x_key!r}")
    flat.sort(key=lambda r: r[x_key])
    if keys is None:
        keys = [k for k in flat[0] if k != x_key and all(isinstance(r.get(k), (int, float)) for r in flat)]
        keys.sort(key=lambda k: (next((i for i, m in enumerate(KEY_METRICS) if k.split(".")[-1] == m),
                                      len(KEY_METRICS)), k))
        keys = keys[:9]
    n = max(1, len(keys))
    ncol = min(3, n)
    nrow = (n + ncol - 1) // ncol
    fig, axes = plt.subplots(nrow, ncol, figsize=(4.2 * ncol, 3.0 * nrow), squeeze=False)
    x = np.array([r[x_key] for r in flat], dtype=float)
    for ax, k in zip(axes.ravel(), keys, strict=False):
        y = np.array([r.get(k, np.nan) for r in flat], dtype=float)
        ax.plot(x, y, "o-", color="#1f77b4")
        ax.set_title(k, fontsize=10)
        ax.set_xlabel(x_key)
        ax.grid(alpha=0.3)
    for ax in axes.ravel()[len(keys):]:
        ax.axis("off")
    fig.suptitle(f"sweep of the detector confidence threshold ({x_key})")
    fig.tight_layout()
    return save_figure(fig, path)


def fig_frame_overlay(path: str | os.PathLike, image: np.ndarray, detections: list[dict], title: str = "") -> Path:
    """One camera image with its detections: kept boxes solid, filtered boxes dashed with the reason.

    ``image`` (H, W, 3) uint8; ``detections`` records with box, cls, conf, kept, reason (optional r_road,
    mapped).
    """
    img = np.asarray(image)
    h, w = img.shape[:2]
    fig, ax = plt.subplots(figsize=(10, 10 * h / max(w, 1) + 0.6))
    ax.imshow(img)
    for d in detections:
        box = d.get("box") or ()
        if len(box) != 4 or any(v is None or not np.isfinite(float(v)) for v in box):
            continue  # an invalid box (the filter's record says why) has nothing to draw
        x1, y1, x2, y2 = (float(v) for v in box)
        code = DEFECT_CODES[int(d["cls"])] if 0 <= int(d.get("cls", -1)) < len(DEFECT_CODES) else "D00"
        kept = bool(d.get("kept", True))
        col = CLASS_COLOURS[code]
        ax.add_patch(Rectangle((x1, y1), x2 - x1, y2 - y1, fill=False, ec=col, lw=2.2 if kept else 1.6,
                               ls="-" if kept else "--"))
        label = f"{code} {float(d.get('conf') or 0.0):.2f}"
        if not kept:
            label += f" ✗ {d.get('reason') or 'filtered'}"
        elif d.get("mapped") is False:
            label += " (not mapped)"
        ax.text(x1, max(y1 - 4, 8), label, color="black", fontsize=8, va="bottom",
                bbox={"fc": col if kept else "white", "ec": col, "alpha": 0.85, "pad": 1.5})
    n_kept = sum(bool(d.get("kept", True)) for d in detections)
    counts = f"{n_kept} kept (solid), {len(detections) - n_kept} filtered (dashed)"
    ax.set_title(f"{title} — {counts}" if title else counts)
    ax.set_xlim(0, w)
    ax.set_ylim(h, 0)
    ax.axis("off")
    return save_figure(fig, path, dpi=90)


def sweep_from_records(records: list[dict], taus: list[float]) -> list[dict]:
    """Figure 13 rows from the per-detection records alone: for each confidence threshold, the
    detections above it, the filter rate FR, on-road precision ORP = 1 - FR and the mapping success
    rate MSR (SPEC §4). The road filter and the mapping of one detection do not depend on the others,
    so raising the threshold only drops records; a threshold below the run's own is skipped, because
    the detections between the two were never filtered or mapped (reason ``low_conf``).
    """
    conf = np.array([np.nan if r.get("conf") is None else float(r["conf"]) for r in records], dtype=np.float64)
    reason = np.array([str(r.get("reason") or ("kept" if r.get("kept") else "off_road")) for r in records])
    kept = np.array([bool(r.get("kept")) for r in records])
    mapped = np.array([bool(r.get("mapped")) for r in records])
    evaluated = np.isin(reason, ("kept", "off_road"))
    low = reason == "low_conf"
    rows = []
    for t in sorted(float(x) for x in taus):
        if np.any(low & (conf >= t)):
            continue
        sel = evaluated & (conf >= t)
        n = int(sel.sum())
        k = int((sel & kept).sum())
        rows.append({"tau_conf": t, "detections": n, "kept": k, "filter_rate": (n - k) / n if n else 0.0,
                     "orp": k / n if n else 0.0, "msr": int((sel & kept & mapped).sum()) / k if k else 0.0})
    return rows


def colour_semantics(labels: np.ndarray, classes: list) -> np.ndarray:
    """(ny, nx) int class ids (-1 or unknown = none) -> (ny, nx, 3) uint8 colours (black where none)."""
    return colour_labels(labels, classes)


def select_overlay_frames(detections: list[dict], k: int = 3) -> list[tuple[int, str]]:
    """The (frame, camera) views worth an overlay: most detections, preferring a mix of kept/filtered."""
    per: dict[tuple[int, str], list[int]] = {}
    for d in detections:
        if d.get("reason") == "low_conf":  # below the detector threshold: not a detection to show
            continue
        key = (int(d["frame"]), str(d["camera"]))
        c = per.setdefault(key, [0, 0])
        c[0 if d.get("kept", True) else 1] += 1
    score = sorted(per, key=lambda v: (-(min(per[v]) > 0), -sum(per[v]), v))
    return score[:k]


__all__ = ["CLASS_COLOURS", "PRIORITY_COLOURS", "colour_semantics", "draw_instances", "fig_bev_overview",
           "fig_frame_overlay", "fig_threshold_sweep", "flatten_metrics", "format_value", "geometry_path",
           "grid_extent", "headline_metrics", "key_metric_lines", "save_figure", "select_overlay_frames",
           "sweep_from_records"]
