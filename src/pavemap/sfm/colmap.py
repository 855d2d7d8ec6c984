"""COLMAP's part of SfM (pycolmap): features with the masks, sequential matching, incremental mapping with the
known intrinsics, an optional intrinsics refinement, and one image folder pycolmap can read."""

from __future__ import annotations

import logging
import os
import shutil
from pathlib import Path

import numpy as np

from pavemap.types import Camera

log = logging.getLogger(__name__)


def colmap_model(pycolmap, work: Path, image_dir: Path, names: list[str], camera: Camera, mask: np.ndarray | None,
                  o: dict):
    """Features (masked), sequential matching and incremental mapping → the largest model, or None."""
    db = work / "database.db"
    if db.exists():
        db.unlink()
    K = camera.K
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "PINHOLE"
    reader.camera_params = f"{K[0, 0]},{K[1, 1]},{K[0, 2] + 0.5},{K[1, 2] + 0.5}"  # COLMAP: pixel corner origin
    if o.get("mask_dir") is not None:
        reader.mask_path = str(o["mask_dir"])  # per image <name>.png: the ego vehicle and what moves, black
    elif mask is not None and mask.any():
        from pavemap.io.egomask import colmap_mask

        reader.camera_mask_path = str(colmap_mask(mask, work / "ego_mask.png"))
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = o["num_threads"]
    extraction.sift.max_num_features = o["max_features"]
    # road surfaces are low-contrast: a lower peak threshold keeps their (few) features
    extraction.sift.peak_threshold = o["peak_threshold"]
    extraction.use_gpu = False
    pycolmap.extract_features(work / "database.db", image_dir, image_names=names,
                              camera_mode=pycolmap.CameraMode.SINGLE, reader_options=reader,
                              extraction_options=extraction, device=pycolmap.Device.cpu)
    pairing = pycolmap.SequentialPairingOptions()
    pairing.overlap = o["overlap"]
    pairing.quadratic_overlap = True
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = o["num_threads"]
    matching.use_gpu = False
    pycolmap.match_sequential(db, matching_options=matching, pairing_options=pairing, device=pycolmap.Device.cpu)
    opts = pycolmap.IncrementalPipelineOptions()
    opts.num_threads = o["num_threads"]
    opts.ba_refine_focal_length = False  # refined once at the end, if at all: early refinement drifts
    opts.ba_refine_principal_point = False
    opts.ba_refine_extra_params = False
    opts.random_seed = o["seed"]
    opts.multiple_models = True  # a bad first model must not end the search; the largest is kept
    # a car moves along its viewing direction: accept forward-motion initial pairs with small angles
    opts.mapper.init_max_forward_motion = 1.0
    rec = None
    # a small initial angle starts forward motion; if its model stays small, ask for a wider pair
    for angle in (o["init_min_tri_angle"], 2 * o["init_min_tri_angle"], 4 * o["init_min_tri_angle"]):
        opts.mapper.init_min_tri_angle = angle
        shutil.rmtree(work / "sparse", ignore_errors=True)
        models = pycolmap.incremental_mapping(db, image_dir, work / "sparse", options=opts)
        best = max(models.values(), key=lambda r: r.num_reg_images()) if models else None
        if best is not None and (rec is None or best.num_reg_images() > rec.num_reg_images()):
            rec = best
        if rec is not None and rec.num_reg_images() >= o["min_share"] * len(names):
            break
        log.info("SfM: init angle %.1f° registered %d of %d; retrying", angle,
                 0 if rec is None else rec.num_reg_images(), len(names))
    if rec is None:
        return None
    if o["refine_intrinsics"]:
        rec = _refine_intrinsics(pycolmap, rec, o)
    return rec


def _refine_intrinsics(pycolmap, rec, o: dict):
    """Bundle adjustment with focal length and principal point free, on a copy; adopted only when sane.

    Forward motion constrains the focal length weakly (it trades against depth), so a refinement that
    moves the focal length by more than ``max_focal_change`` (or the principal point by more than 5 % of
    the image) or does not lower the reprojection error is reported and rejected.
    """
    trial = pycolmap.Reconstruction(rec)
    ba = pycolmap.BundleAdjustmentOptions()
    ba.refine_focal_length = True
    ba.refine_principal_point = True
    ba.refine_extra_params = False
    pycolmap.bundle_adjustment(trial, ba)
    c0 = next(iter(rec.cameras.values()))
    c1 = next(iter(trial.cameras.values()))
    p0, p1 = np.asarray(c0.params[:4], float), np.asarray(c1.params[:4], float)
    e0, e1 = rec.compute_mean_reprojection_error(), trial.compute_mean_reprojection_error()
    df = abs(p1[0] / p0[0] - 1.0)
    dpp = float(np.abs(p1[2:4] - p0[2:4]).max()) / max(c0.width, c0.height)
    ok = df <= o["max_focal_change"] and dpp <= 0.05 and e1 <= e0
    o["intrinsics"] = {"fx": round(p1[0], 2), "fy": round(p1[1], 2), "cx": round(p1[2] - 0.5, 2),
                       "cy": round(p1[3] - 0.5, 2), "focal_change": round(df, 4), "reproj_px": [round(e0, 3),
                       round(e1, 3)], "adopted": bool(ok)}
    log.info("SfM intrinsics refinement: %s", o["intrinsics"])
    return trial if ok else rec


def prepare_images(images: list[Path], work: Path) -> tuple[Path, list[str]]:
    """One folder pycolmap can read and the image names in it (links when the images are spread out)."""
    folders = {p.parent.resolve() for p in images}
    if len(folders) == 1:
        return folders.pop(), [p.name for p in images]
    image_dir = work / "images"
    image_dir.mkdir(exist_ok=True)
    names = []
    for i, p in enumerate(images):
        name = f"{i:06d}{p.suffix.lower()}"
        if not (image_dir / name).exists():
            os.symlink(p.resolve(), image_dir / name)
        names.append(name)
    return image_dir, names


__all__ = ["colmap_model", "prepare_images"]
