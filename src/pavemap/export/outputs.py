"""The outputs people use, from a run's results: the GeoJSON, CSV and GeoTIFF layers, the figures and the report
(:func:`write_outputs`; the run folder's other files are :mod:`pavemap.export.run_files`')."""

from __future__ import annotations

import logging
import os
import shutil
from collections.abc import Callable
from pathlib import Path

import numpy as np
from tqdm.auto import tqdm

from pavemap.errors import PavemapError, SequenceError
from pavemap.export.geojson import write_geojson
from pavemap.export.tables import write_csv
from pavemap.geometry.grid import GridSpec
from pavemap.io.atomic import atomic_path, atomic_write_json
from pavemap.types import DefectInstance, GeoOrigin, Sequence

log = logging.getLogger("pavemap")


def write_png(path: str | os.PathLike, img: np.ndarray) -> Path:
    """Write an (H, W, 3|4) uint8 image (or (H, W)) as PNG atomically."""
    from PIL import Image

    a = np.asarray(img)
    if a.dtype != np.uint8:
        raise PavemapError(f"{path}: image must be uint8, got {a.dtype}")
    with atomic_path(path) as tmp:
        Image.fromarray(np.ascontiguousarray(a)).save(tmp, format="PNG", compress_level=4)
    return Path(path)


def _check_bev(name: str, img: np.ndarray | None, mesh_grid: GridSpec | None) -> np.ndarray | None:
    if img is None:
        return None
    a = np.asarray(img)
    if a.ndim != 3 or a.shape[2] != 3 or a.dtype != np.uint8:
        raise PavemapError(f"{name} must be (ny, nx, 3) uint8, got {a.shape} {a.dtype}")
    if mesh_grid is None:
        raise PavemapError(f"{name} given without its mesh grid")
    from pavemap.export.geotiff import check_grid

    check_grid(mesh_grid, a.shape[:2], f"{name} grid")
    return a


def _opt(output: object | None, name: str, default):
    """A field of the output settings (an OutputConfig dataclass or a plain dict)."""
    if output is None:
        return default
    if isinstance(output, dict):
        return output.get(name, default)
    return getattr(output, name, default)


def _overlay_frames(seq: Sequence, detections: list[dict], k: int) -> list[dict]:
    """Load the camera images of the ``k`` views best worth an overlay (missing images are skipped)."""
    from pavemap.export.figures import select_overlay_frames
    from pavemap.io.sequence import load_rgb

    frames = seq.frame_by_index()
    out = []
    for f, cam in select_overlay_frames(detections, k):
        view = frames[f].views.get(cam) if f in frames else None
        if view is None:
            continue
        try:
            out.append({"frame": f, "camera": cam, "image": load_rgb(seq.path(view.image))})
        except (SequenceError, ValueError) as e:
            log.warning("overlay of frame %d %s skipped: %s", f, cam, e)
    return out


def _output_folder(out: Path) -> Path:
    try:
        out.mkdir(parents=True, exist_ok=True)
        (out / "figures").mkdir(exist_ok=True)
    except OSError as e:
        raise PavemapError(f"{out}: cannot create the output folder ({e.strerror or e})") from None
    if not os.access(out, os.W_OK):
        raise PavemapError(f"{out}: output folder is not writable")
    return out


def _copy_mesh(src: Path, dst: Path) -> Path:
    """Stage 1's mesh file into the run folder (atomically; nothing to do when it is already there)."""
    if not src.is_file():
        raise PavemapError(f"{src}: road mesh not found")
    if src.resolve() != dst.resolve():
        with atomic_path(dst) as tmp:
            shutil.copyfile(src, tmp)
    return dst


def _figures_extra(figures_extra: dict | None) -> dict:
    """A copy of :func:`write_outputs`' ``figures_extra``; an unknown key is refused."""
    extra = dict(figures_extra or {})
    unknown = set(extra) - {"sweep", "frames", "images"}
    if unknown:
        raise PavemapError(f"figures_extra: unknown key(s) {sorted(unknown)}; expected sweep, frames, images")
    return extra


def _sweep_and_frames(extra: dict, seq: Sequence | None, detections: list[dict] | None, output: object | None,
                      want_figures: bool) -> tuple[list | None, list[dict]]:
    """The threshold sweep rows and the views to overlay: given in ``figures_extra`` or derived."""
    from pavemap.export.figures import sweep_from_records

    sweep = extra.get("sweep")
    if sweep is None and detections and _opt(output, "sweep_tau_conf", None):
        sweep = sweep_from_records(detections, list(_opt(output, "sweep_tau_conf", ())))
    frames = extra.get("frames")
    if frames is None and seq is not None and detections and want_figures:
        k = int(_opt(output, "overlay_frames", 3) or 0)
        frames = _overlay_frames(seq, detections, k) if k > 0 else []
    return sweep, (list(frames or []) if want_figures else [])


def _sweep_and_frame_figures(fig_dir: Path, sweep: list | None, frames: list[dict], detections: list[dict],
                             step) -> dict[str, Path]:  # noqa: ANN001
    """The threshold sweep and the per-view overlays: {caption: png path}."""
    from pavemap.export.figures import fig_frame_overlay, fig_threshold_sweep

    figs: dict[str, Path] = {}
    if sweep:
        figs["detections against the confidence threshold (Figure 13 style)"] = fig_threshold_sweep(
            fig_dir / "threshold_sweep.png", list(sweep))
        step("figures/threshold_sweep.png")
    for fr in frames:
        f, cam = int(fr["frame"]), str(fr["camera"])
        dets = [d for d in detections if int(d["frame"]) == f and str(d["camera"]) == cam
                and d.get("reason") != "low_conf"]
        name = f"frame_{f:06d}_{cam}.png"
        figs[f"frame {f}, {cam}: kept (solid) and filtered (dashed) detections"] = fig_frame_overlay(
            fig_dir / name, fr["image"], dets, title=f"frame {f} · {cam}")
        step(f"figures/{name}")
    return figs


def write_outputs(out_dir: str | os.PathLike, instances: list[DefectInstance], prob_map: np.ndarray,
                  class_maps: np.ndarray, grid: GridSpec, bev_rgb: np.ndarray | None, bev_semantic: np.ndarray | None,
                  mesh_grid: GridSpec | None, geo_origin: GeoOrigin | None, metrics: dict | None,
                  config: dict | None, detections: list[dict] | None, figures_extra: dict | None = None, *,
                  seq: Sequence | None = None, output: object | None = None,
                  mesh_path: str | os.PathLike | None = None, trajectory: np.ndarray | None = None,
                  title: str | None = None, progress: bool = True,
                  written: dict[str, Path] | None = None, valid: np.ndarray | None = None,
                  segments: list | None = None) -> dict[str, Path]:
    """Write every output of a run into ``out_dir``; returns {name: path}.

    Arrays: ``prob_map`` (H, W) float and ``class_maps`` (4, H, W) float on ``grid`` (a
    :class:`~pavemap.geometry.grid.GridSpec`; rows go +y); ``bev_rgb``/``bev_semantic`` (ny, nx, 3)
    uint8 on ``mesh_grid``. ``written``: files of the same run another export writer owns
    (:func:`pavemap.export.run_files.write_run`): listed in the report, never written here.
    ``detections``: records {frame, camera, box, cls, conf, kept, reason, r_road, mapped}.
    ``figures_extra`` (all optional):
      - "sweep": rows [{"tau_conf": .., metric: ..}] -> figures/threshold_sweep.png (Figure 13 style);
        default: computed from the detection records at ``output.sweep_tau_conf``
      - "frames": [{"frame": int, "camera": str, "image": (H, W, 3) uint8}] -> figures/frame_*.png overlays
        of that view's detections; default: the ``output.overlay_frames`` best views, loaded from ``seq``
      - "images": {caption: png path} of figures made elsewhere, embedded in the report
    ``seq``: the Sequence (overlay images, trajectory and name for the report).
    ``output``: OutputConfig or dict: figures (bool), report (bool), overlay_frames (int), sweep_tau_conf.
    ``mesh_path``: stage 1's road_mesh.ply, copied into ``out_dir`` when it lives elsewhere.
    ``trajectory`` (F, 2|3) world metres, drawn on the report map (default: the sequence's).
    ``valid`` (H, W) bool on ``grid``: the surveyed cells (the GeoTIFF's nodata elsewhere; default all).
    ``segments``: the road segments (``FusionResult.segments``) drawn as the report's segment strip.
    Layers: ``defects.geojson`` only with ``geo_origin`` (GeoJSON is WGS84), ``survey.gpkg`` always
    (:mod:`pavemap.export.gis`; CRS ``output.crs``, extra formats ``output.extra_formats``).
    """
    from pavemap.export.report import write_report  # loads here, not at import: `import pavemap` stays fast

    out = _output_folder(Path(out_dir))
    bev_rgb = _check_bev("bev_rgb", bev_rgb, mesh_grid)
    bev_semantic = _check_bev("bev_semantic", bev_semantic, mesh_grid)
    extra = _figures_extra(figures_extra)
    detections = list(detections) if detections is not None else None
    want_figures = bool(_opt(output, "figures", True))
    want_report = bool(_opt(output, "report", True))
    if title is None:
        title = f"pavemap defect report — {seq.name}" if seq is not None and seq.name else "pavemap defect report"
    if trajectory is None and seq is not None and seq.frames:
        trajectory = seq.trajectory()
    sweep, frames = _sweep_and_frames(extra, seq, detections, output, want_figures)
    done = dict(written or {})
    steps = 4 + (mesh_path is not None) + want_report + want_figures * (1 + len(frames) + bool(sweep))
    bar = tqdm(total=steps, desc="outputs", unit="file", disable=not progress, leave=False)

    def step(name: str) -> None:
        bar.set_postfix_str(name)
        bar.update(1)

    try:
        paths = _write_layers(out, done, instances, prob_map, class_maps, grid, geo_origin, output, valid, seq, step)
        paths.update(_write_images(out, done, bev_rgb, bev_semantic, metrics, mesh_path, step))
        figs: dict[str, Path] = {}
        if want_figures:
            figs.update(_write_figures(out, bev_rgb, bev_semantic, mesh_grid, instances, metrics, prob_map, grid,
                                       title, sweep, frames, detections or [], step))
        for caption, p in (extra.get("images") or {}).items():
            figs[str(caption)] = Path(p)
        for k, p in figs.items():
            paths[f"figure:{k}"] = p
        files = {k: p for k, p in {**done, **paths}.items() if not k.startswith("figure:")}
        if want_report:
            paths["report.html"] = write_report(
                out, instances, bev_rgb=bev_rgb, bev_semantic=bev_semantic, mesh_grid=mesh_grid,
                prob_map=prob_map, grid=grid, geo_origin=geo_origin, metrics=metrics, config=config,
                detections=detections, figures=figs, files=files, trajectory=trajectory, title=title,
                segments=segments)
            step("report.html")
    except OSError as e:  # read-only, disk full …: say which file (the atomic writer names the final one)
        where = f": {e.filename}" if e.filename else ""
        raise PavemapError(f"{out}: cannot write outputs ({e.strerror or e}{where})") from None
    finally:
        bar.close()
    return paths


def _write_layers(out: Path, done: dict[str, Path], instances: list[DefectInstance], prob_map: np.ndarray,
                  class_maps: np.ndarray, grid: GridSpec, geo_origin: GeoOrigin | None, output: object | None,
                  valid: np.ndarray | None, seq: Sequence | None, step: Callable[[str], None]) -> dict[str, Path]:
    """The defect layers (GeoJSON with ``geo_origin``, survey.gpkg), defects.csv and defect_map.tif, skipping
    what ``done`` lists; arrays as :func:`write_outputs` takes them."""
    from pavemap.export.geotiff import write_geotiff  # rasterio loads here, not at import

    paths: dict[str, Path] = {}
    if "defects.geojson" not in done and geo_origin is not None:
        paths["defects.geojson"] = write_geojson(out / "defects.geojson", instances, geo_origin)
    if "survey.gpkg" not in done:
        from pavemap.export.gis import write_gis

        paths.update(write_gis(out, instances, geo_origin=geo_origin, crs=_opt(output, "crs", "auto"), seq=seq,
                               formats=tuple(_opt(output, "extra_formats", ())),
                               vehicle=_opt(output, "vehicle", "")))
    step("defect layers")
    paths["defects.csv"] = write_csv(out / "defects.csv", instances, geo_origin)
    step("defects.csv")
    paths["defect_map.tif"] = write_geotiff(out / "defect_map.tif", prob_map, class_maps, grid, geo_origin,
                                            crs=_opt(output, "crs", "auto"), valid=valid,
                                            name=seq.name if seq is not None else "")
    step("defect_map.tif")
    return paths


def _write_images(out: Path, done: dict[str, Path], bev_rgb: np.ndarray | None, bev_semantic: np.ndarray | None,
                  metrics: dict | None, mesh_path: str | os.PathLike | None,
                  step: Callable[[str], None]) -> dict[str, Path]:
    """The BEV PNGs (``bev_rgb`` / ``bev_semantic`` (ny, nx, 3) uint8, rows +y), metrics.json unless ``done``
    lists it, and the road mesh (copied from ``mesh_path``, or listed when already in ``out``)."""
    paths: dict[str, Path] = {}
    # PNGs are north-up like any picture: our rows go +y, so flip
    if bev_rgb is not None:
        paths["bev_rgb.png"] = write_png(out / "bev_rgb.png", bev_rgb[::-1])
    if bev_semantic is not None:
        paths["bev_semantic.png"] = write_png(out / "bev_semantic.png", bev_semantic[::-1])
    if metrics is not None and "metrics.json" not in done:
        paths["metrics.json"] = atomic_write_json(out / "metrics.json", metrics)
    step("bev images")
    if mesh_path is not None:
        paths["road_mesh.ply"] = _copy_mesh(Path(mesh_path), out / "road_mesh.ply")
        step("road_mesh.ply")
    elif (out / "road_mesh.ply").is_file():
        paths["road_mesh.ply"] = out / "road_mesh.ply"
    return paths


def _write_figures(out: Path, bev_rgb: np.ndarray | None, bev_semantic: np.ndarray | None,
                   mesh_grid: GridSpec | None, instances: list[DefectInstance], metrics: dict | None,
                   prob_map: np.ndarray, grid: GridSpec, title: str, sweep: list | None, frames: list[dict],
                   detections: list[dict], step: Callable[[str], None]) -> dict[str, Path]:
    """figures/: the BEV overview (Figure 11 layout), then the threshold sweep and the frame overlays;
    {caption: path}."""
    from pavemap.export.figures import fig_bev_overview  # matplotlib loads here, not at import

    figs = {"Figure 11 layout: BEV RGB, semantics, defects, statistics": fig_bev_overview(
        out / "figures" / "bev_overview.png", bev_rgb, bev_semantic, mesh_grid, instances, metrics,
        prob_map, grid, title=title)}
    step("figures/bev_overview.png")
    figs.update(_sweep_and_frame_figures(out / "figures", sweep, frames, detections, step))
    return figs


__all__ = ["write_outputs", "write_png"]
