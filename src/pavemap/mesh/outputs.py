"""Stage-1 files: mesh.ply, BEV rasters (PNG + .npy), curves, metrics.json and mesh.npz
(the checkpoint: :mod:`pavemap.mesh.checkpoint`).

Array convention: ``.npy`` rasters are in grid order (row = y index, as ``HeightField``); PNGs are
flipped so that +y (north when the world is ENU) is up, for people. ``grid.json`` holds the grid's
:meth:`pavemap.geometry.GridSpec.to_dict`.
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from pavemap.errors import PavemapError
from pavemap.geometry import HeightField
from pavemap.io.atomic import atomic_path, atomic_write_bytes, atomic_write_json
from pavemap.mesh.model import RoadMesh
from pavemap.palette import colour_labels
from pavemap.types import SemanticClass

MESH_FILE = "mesh.npz"

def bev_rasters(mesh: RoadMesh, classes: list[SemanticClass]) -> dict[str, np.ndarray]:
    """Grid-order rasters: rgb (ny, nx, 3) uint8, semantic (ny, nx) int16 class id (-1 none),
    semantic_rgb (ny, nx, 3) uint8, height (ny, nx) float32 (NaN off the crop), valid (ny, nx) bool,
    observed (ny, nx) bool (a training pixel or ground point reaches the vertex; the crop when unknown),
    contested (ny, nx) bool (some views disagree with the texture there: it may hold a vehicle) or None when
    the mesh was not checked (not checked is not clean: no raster is written then)."""
    valid = mesh.surface.valid.cpu().numpy()
    vid = mesh.vertex_ids.cpu().numpy()
    rgb = np.zeros((valid.size, 3), np.uint8)
    rgb[vid] = (mesh.rgb.clamp(0, 1).cpu().numpy() * 255 + 0.5).astype(np.uint8)
    rgb = rgb.reshape(*valid.shape, 3)
    labels = np.full(valid.size, -1, np.int16)
    labels[vid] = mesh.vertex_labels().cpu().numpy()
    labels = labels.reshape(valid.shape)
    sem_rgb = colour_labels(labels, classes)
    if not mesh.has_semantics:
        sem_rgb[valid] = (128, 128, 128)
    h = mesh.surface.heights.detach().cpu().numpy().astype(np.float32).copy()
    h[~valid] = np.nan
    observed = valid if mesh.observed is None else mesh.observed.cpu().numpy().astype(bool) & valid
    contested = None if mesh.contested is None else mesh.contested.cpu().numpy().astype(bool) & valid
    return {"rgb": rgb, "semantic": labels, "semantic_rgb": sem_rgb, "height": h, "valid": valid,
            "observed": observed, "contested": contested}


def _png_bytes(a: np.ndarray) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(a).save(buf, format="PNG")
    return buf.getvalue()


def _save_npy(path: Path, a: np.ndarray) -> None:
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        np.save(f, a)


def _height_png(h: np.ndarray) -> np.ndarray:
    import matplotlib

    ok = np.isfinite(h)
    out = np.zeros((*h.shape, 3), dtype=np.uint8)
    if ok.any():
        lo, hi = np.percentile(h[ok], [1, 99])
        t = np.clip((h - lo) / max(hi - lo, 1e-6), 0, 1)
        out[ok] = (matplotlib.colormaps["viridis"](t[ok])[:, :3] * 255).astype(np.uint8)
    return out


def write_mesh_ply(path: Path, mesh: RoadMesh) -> None:
    """Kept vertices in world coordinates with vertex colours and the uchar property ``observed`` (1: a
    training pixel or ground point reaches it; absent when unknown), faces of kept triangles (trimesh)."""
    import trimesh

    s = mesh.surface
    vid = mesh.vertex_ids.cpu()
    vid_np = vid.numpy()
    verts = np.stack([s.x0 + (vid_np % s.nx) * s.res, s.y0 + (vid_np // s.nx) * s.res,
                      s.heights.detach().cpu().reshape(-1)[vid].double().numpy()], 1)
    faces = mesh.vertex_of(s.faces(valid_only=True).cpu()).numpy()  # kept triangles: every corner a vertex
    rgb = (mesh.rgb.clamp(0, 1).cpu().numpy() * 255 + 0.5).astype(np.uint8)
    colours = np.concatenate([rgb, np.full((rgb.shape[0], 1), 255, np.uint8)], 1)
    tm = trimesh.Trimesh(vertices=verts, faces=faces, vertex_colors=colours, process=False)
    if mesh.observed is not None:
        tm.vertex_attributes["observed"] = mesh.observed.reshape(-1).cpu().numpy()[vid.numpy()].astype(np.uint8)
    atomic_write_bytes(path, tm.export(file_type="ply"))


def _curves_png(path: Path, history: list[dict]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ep = [h["epoch"] for h in history]
    fig, ax = plt.subplots(1, 2, figsize=(9, 3.2))
    ax[0].plot(ep, [h["loss"] for h in history], "o-", label="total")
    ax[0].plot(ep, [h["l_rgb"] for h in history], "s-", label="L1 rgb")
    ax[0].plot(ep, [h["l_sem"] for h in history], "^-", label="CE sem")
    ax[0].set_xlabel("epoch")
    ax[0].set_ylabel("loss")
    ax[0].legend()
    ax[1].plot(ep, [h["train_psnr"] for h in history], "o-", label="train (road)")
    ax[1].plot(ep, [h["eval_psnr"] for h in history], "s-", label="held-out (road)")
    ax[1].set_xlabel("epoch")
    ax[1].set_ylabel("PSNR dB")
    ax[1].legend()
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100)
    plt.close(fig)
    atomic_write_bytes(path, buf.getvalue())


def save_mesh(out: Path, mesh: RoadMesh) -> None:
    """mesh.npz: grid, crop, heights and compact per-vertex rgb / logits (what load_mesh reads)."""
    s = mesh.surface
    valid = s.valid.cpu().numpy()
    with atomic_path(out / MESH_FILE) as tmp, open(tmp, "wb") as f:
        np.savez_compressed(
            f, x0=s.x0, y0=s.y0, res=s.res, heights=s.heights.detach().cpu().numpy().astype(np.float32),
            valid=valid, rgb=mesh.rgb.cpu().numpy().astype(np.float32),
            sem_logits=mesh.sem_logits.cpu().numpy().astype(np.float32),
            class_ids=np.asarray(mesh.class_ids, dtype=np.int64), has_semantics=mesh.has_semantics,
            **({} if mesh.observed is None else {"observed": mesh.observed.cpu().numpy().astype(bool)}),
            **({} if mesh.contested is None else {"contested": mesh.contested.cpu().numpy().astype(bool)}),
            **({} if mesh.samples is None else {"samples": np.asarray(mesh.samples, np.float32).reshape(-1, 3)}))


def load_mesh(out_dir: Path) -> RoadMesh:
    """Read the RoadMesh a stage-1 run wrote to ``out_dir`` (``mesh.npz``)."""
    f = Path(out_dir) / MESH_FILE
    if not f.is_file():
        raise PavemapError(f"{f}: not found; run `pavemap reconstruct SEQ --out {out_dir}` first")
    try:
        z = np.load(f)
        valid = z["valid"].astype(bool)
        surf = HeightField(float(z["x0"]), float(z["y0"]), float(z["res"]),
                           torch.from_numpy(z["heights"].astype(np.float32)), torch.from_numpy(valid))
        observed = torch.from_numpy(z["observed"].astype(bool)) if "observed" in z.files else None
        samples = z["samples"].astype(np.float32).reshape(-1, 3) if "samples" in z.files else None
        contested = torch.from_numpy(z["contested"].astype(bool)) if "contested" in z.files else None
        return RoadMesh(surf, torch.from_numpy(z["rgb"].astype(np.float32)),
                        torch.from_numpy(z["sem_logits"].astype(np.float32)), [int(c) for c in z["class_ids"]],
                        bool(z["has_semantics"]), observed, samples, contested)
    except (KeyError, ValueError, OSError) as e:
        raise PavemapError(f"{f}: not a pavemap mesh file ({e})") from None


def write_outputs(out: Path, mesh: RoadMesh, metrics: dict, classes: list[SemanticClass]) -> dict[str, Path]:
    """All stage-1 files into ``out``; returns name -> path."""
    out.mkdir(parents=True, exist_ok=True)
    r = bev_rasters(mesh, classes)
    paths = {}
    save_mesh(out, mesh)
    paths["mesh.npz"] = out / MESH_FILE
    write_mesh_ply(out / "mesh.ply", mesh)
    paths["mesh.ply"] = out / "mesh.ply"
    for name, img in (("bev_rgb.png", r["rgb"]), ("bev_semantic.png", r["semantic_rgb"]),
                      ("bev_height.png", _height_png(r["height"]))):
        atomic_write_bytes(out / name, _png_bytes(np.ascontiguousarray(img[::-1])))
        paths[name] = out / name
    for name in ("rgb", "semantic", "height", "valid", "observed", "contested"):
        if r[name] is None:
            continue
        _save_npy(out / f"bev_{name}.npy", r[name])
        paths[f"bev_{name}.npy"] = out / f"bev_{name}.npy"
    atomic_write_json(out / "grid.json", mesh.grid.to_dict())
    if metrics.get("history"):
        _curves_png(out / "curves.png", metrics["history"])
        paths["curves.png"] = out / "curves.png"
    atomic_write_json(out / "metrics.json", _json_safe(metrics))
    paths["metrics.json"] = out / "metrics.json"
    return paths


def _json_safe(o):
    """NaN/inf -> None (JSON has no NaN)."""
    if isinstance(o, dict):
        return {k: _json_safe(v) for k, v in o.items()}
    if isinstance(o, list | tuple):
        return [_json_safe(v) for v in o]
    if isinstance(o, float | np.floating) and not np.isfinite(o):
        return None
    return o
