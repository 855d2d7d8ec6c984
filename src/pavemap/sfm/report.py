"""What SfM measured, written beside the sequence on success *and* on refusal: ``sfm.json`` and ``sfm.png``.

A refused clip must tell its user what went wrong and which part of it was usable; a kept clip must say what
was dropped and how sure the path is. The JSON holds the figures (registered and dropped frames with the
reason, the parts, the checks and their limits, each step by SfM and by the road, the camera heights); the
figure shows the path from above (dropped frames marked where SfM placed them) and the camera's height over
the road along it.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from pavemap.io.atomic import atomic_path, atomic_write_json
from pavemap.sfm.checks import SfmChecks

log = logging.getLogger(__name__)

SFM_REPORT = "sfm.json"
SFM_FIGURE = "sfm.png"


def _public(info: dict) -> dict:
    return {k: _json_safe(v) for k, v in info.items() if not k.startswith("_")}


def _json_safe(v: object) -> object:
    """Plain JSON: NaN / inf (a figure that was not measured) become null, numpy scalars and arrays plain."""
    if isinstance(v, dict):
        return {str(k): _json_safe(x) for k, x in v.items()}
    if isinstance(v, list | tuple | np.ndarray):
        return [_json_safe(x) for x in (v.tolist() if isinstance(v, np.ndarray) else v)]
    if isinstance(v, np.generic):
        v = v.item()
    if isinstance(v, float) and not np.isfinite(v):
        return None
    return v


def write_sfm_report(info: dict, out: Path, T_world_cam: np.ndarray | None = None,
                     registered: np.ndarray | None = None, checks: SfmChecks | None = None,
                     scale: float | None = None) -> list[Path]:
    """``out/sfm.json`` and ``out/sfm.png`` (each written whole or not at all); returns their paths.

    ``info``: what :func:`pavemap.sfm.pipeline.sfm_poses` measured (``status`` "ok" or "refused" with its
    ``reason``); ``T_world_cam`` (N, 4, 4) / ``registered`` (N,) the kept poses, when there are any. The limits
    of the checks go in the JSON beside the figures they bound."""
    from dataclasses import asdict

    out = Path(out)
    body = {"status": info.get("status", "ok"), **_public(info)}
    if scale is not None:
        body["scale_m_per_unit"] = _json_safe(float(scale))
    body["limits"] = asdict(checks or SfmChecks())
    paths = [atomic_write_json(out / SFM_REPORT, body)]
    try:
        paths.append(_figure(info, out / SFM_FIGURE, T_world_cam, registered))
    except Exception as e:  # noqa: BLE001 - a figure that cannot be drawn must not hide the JSON's diagnosis
        log.warning("SfM: the diagnosis figure could not be drawn (%s); %s has the figures", e, paths[0])
    return paths


def _figure(info: dict, path: Path, T: np.ndarray | None, registered: np.ndarray | None) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax, bx) = plt.subplots(1, 2, figsize=(12, 5), gridspec_kw={"width_ratios": [1.2, 1]})
    status = info.get("status", "ok")
    n = int(info.get("images", 0))
    kept = np.zeros(n, dtype=bool) if registered is None else np.asarray(registered, bool)
    title = (f"kept {int(kept.sum())} of {n} frames ({info.get('method', 'SfM')})" if status == "ok"
             else "refused: " + _wrap(str(info.get("reason", "")), 70))
    fig.suptitle(title, fontsize=10, color="black" if status == "ok" else "firebrick")
    _path_panel(ax, info, T, kept)
    _height_panel(bx, info)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)
    return path


def _wrap(text: str, width: int) -> str:
    import textwrap

    return "\n".join(textwrap.wrap(text, width)[:3])


def _path_panel(ax, info: dict, T: np.ndarray | None, kept: np.ndarray) -> None:  # noqa: ANN001
    """The path from above: kept frames joined, dropped frames as red crosses where SfM put them."""
    dropped = {int(k): v for k, v in (info.get("dropped") or {}).items()}
    sfm = info.get("_poses_sfm")
    drawn = False
    if T is not None and kept.any():
        C = T[kept, :3, 3]
        ax.plot(C[:, 0], C[:, 1], "-o", ms=3, color="tab:blue", label="kept")
        ax.annotate("start", C[0, :2], fontsize=8)
        drawn = True
    if sfm is not None and dropped:
        idx = [i for i in dropped if i < len(sfm) and np.isfinite(sfm[i, :3, 3]).all()]
        if idx:
            P = sfm[idx, :3, 3]
            ax.plot(P[:, 0], P[:, 1], "x", color="firebrick", label="dropped (where SfM put it)")
            drawn = True
    if dropped:
        first = next(iter(dropped.values()))
        ax.text(0.01, 0.01, _wrap(f"{len(dropped)} frames dropped, e.g. frame {next(iter(dropped))}: {first}", 60),
                transform=ax.transAxes, fontsize=7, color="firebrick", va="bottom")
    if not drawn:
        ax.text(0.5, 0.5, "no path: nothing registered", ha="center", transform=ax.transAxes)
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x (m, along the drive)")
    ax.set_ylabel("y (m, left)")
    ax.set_title("path from above", fontsize=9)
    if drawn:
        ax.legend(fontsize=7, loc="upper right")


def _height_panel(bx, info: dict) -> None:  # noqa: ANN001
    """The camera's height over the road under it along the path, with the mount height and the check's band."""
    checks = info.get("checks") or {}
    h = [np.nan if x is None else x for x in checks.get("heights_m", [])]
    target = info.get("camera_height_m")
    if h and np.isfinite(h).any():
        bx.plot(range(len(h)), h, "o-", ms=3, color="tab:green", label="measured over the road")
    else:
        bx.text(0.5, 0.5, "road under the path not measured", ha="center", transform=bx.transAxes)
    if target:
        bx.axhline(target, color="k", lw=1, label=f"mount height {target:g} m")
        bx.axhspan(target - 0.05, target + 0.05, color="k", alpha=0.08, label="+/- 5 cm")
    bx.set_xlabel("kept frame")
    bx.set_ylabel("camera height over the road (m)")
    bx.set_title(f"scale: {info.get('scale_source', 'not set')}", fontsize=9)
    bx.legend(fontsize=7, loc="upper right")


__all__ = ["SFM_FIGURE", "SFM_REPORT", "write_sfm_report"]
