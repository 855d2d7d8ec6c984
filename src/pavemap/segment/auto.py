"""Semantics for a drive that has none: the ESPNet segmenter by default, or a fallback the console states.

``--segmenter`` values (import and run): ``auto`` (the default: :data:`~pavemap.segment.espnet.DEFAULT`
when its weights are found and the images are in colour, else the fallback, said on the console),
``espnet`` / ``espnetv2`` (required: missing weights or grey images are an error), ``none`` (no
segmenter), at import also ``corridor`` (the trajectory-corridor fallback) and an ultralytics
semantic-segmentation ``.pt`` file.
"""

from __future__ import annotations

import copy
import json
import logging
import os
from pathlib import Path

import numpy as np

from pavemap.errors import PavemapError
from pavemap.io.atomic import atomic_write_json
from pavemap.io.sequence import load_rgb
from pavemap.segment import segment_sequence
from pavemap.segment.espnet import ARCHS, DEFAULT, EspnetSegmenter, find_weights, is_grey
from pavemap.types import Sequence

log = logging.getLogger(__name__)

CHOICES = ("auto", *ARCHS, "none")
STAMP = "semantics/segmenter.json"


class GreyImagesError(PavemapError):
    """The drive's images are grey (e.g. KITTI's cameras 0 / 1): a Cityscapes colour model cannot label them."""


class WeightsMissingError(PavemapError):
    """No weight file for the asked network."""


def arch_of(spec: str) -> str:
    """The network an ``--segmenter`` value names (``auto`` → the default one)."""
    return DEFAULT if spec == "auto" else spec


def check_colour(seq: Sequence) -> None:
    """Raise :class:`GreyImagesError` naming the first camera's image whose channels are all equal."""
    for cam in seq.cameras:
        view = next((f.views[cam] for f in seq.frames if cam in f.views), None)
        if view is not None and is_grey(load_rgb(seq.path(view.image))):
            raise GreyImagesError(
                f"{seq.path(view.image)}: grey image (camera {cam}); the Cityscapes segmenter needs colour images "
                "(KITTI: --camera 2), or give --labels, or --segmenter none / corridor")


def camera_ego_masks(seq: Sequence, detect: bool = True) -> dict[str, np.ndarray | None]:
    """Per camera, (H, W) bool True on the ego vehicle: the stored ``masks/<camera>.png``, else (``detect``,
    ≥ 6 frames) found in the images (:func:`pavemap.io.egomask.detect_ego_mask`), else None."""
    from pavemap.io.egomask import detect_ego_mask, ego_mask_at, mask_report

    out: dict[str, np.ndarray | None] = {}
    for cam, c in seq.cameras.items():
        m = ego_mask_at(seq, cam, c.width, c.height) if c.ego_mask else None
        source = "stored"
        if m is None and detect:
            imgs = [seq.path(f.views[cam].image) for f in seq.frames if cam in f.views]
            m, source = (detect_ego_mask(imgs, c.width, c.height), "auto") if len(imgs) >= 6 else (None, "")
        if m is not None and m.any():
            log.info("camera %s: %s", cam, mask_report(m, source).describe())
            out[cam] = m
        else:
            out[cam] = None
    return out


def espnet_semantics(seq: Sequence, arch: str = DEFAULT, weights: str | os.PathLike | None = None,
                     device: str = "auto", out_root: str | os.PathLike | None = None, batch: int = 4,
                     width: int | None = None, segmenter: EspnetSegmenter | None = None,
                     camera_height: float | None = None, plane_check: bool = True, road_vote: bool = True
                     ) -> Sequence:
    """Label every view of ``seq`` with the ESPNet / ESPNetv2 segmenter, the ego vehicle masked (see
    :func:`segment_sequence` for ``out_root``). Grey images or missing weights: a one-line error.
    ``segmenter``: one already made for this ``arch`` and ``width`` (the import's, which labelled SfM's
    vehicle masks: what it remembers is not labelled again). ``plane_check``: then relabel the road pixels that
    are off the road plane ``camera_height`` below the cameras (None: each camera's ``height_m``;
    :mod:`pavemap.segment.plane_check`), said on the console."""
    check_colour(seq)
    try:
        find_weights(arch, weights)
    except PavemapError as e:
        raise WeightsMissingError(str(e)) from None
    same = (segmenter is not None and segmenter.arch.name == arch and segmenter.width == width
            and segmenter.path == find_weights(arch, weights))
    seg = segmenter if same else EspnetSegmenter(arch, weights, device, width)
    seq = segment_sequence(seq, seg, batch, camera_ego_masks(seq), out_root)
    if plane_check:
        from pavemap.segment.plane_check import plane_check_sequence

        rep = plane_check_sequence(seq, camera_height)
        log.info("%s", rep.describe())
        if rep.skipped:
            log.info("plane check skipped: %s", "; ".join(rep.skipped))
    if road_vote:
        from pavemap.segment.road_vote import road_vote_sequence

        vote = road_vote_sequence(seq, camera_height)
        log.info("%s", vote.describe())
        if vote.skipped:
            log.info("road vote skipped: %s", "; ".join(vote.skipped))
    return seq


def has_semantics(seq: Sequence) -> bool:
    return any(v.semantics for f in seq.frames for v in f.views.values())


def _stamp(seq: Sequence, arch: str, path: Path, camera_height: float | None) -> dict:
    from pavemap.io.hashes import hash_sequence
    from pavemap.version import code_version

    st = path.stat()
    return {"arch": arch, "weights": str(path.resolve()), "size": st.st_size, "mtime_ns": st.st_mtime_ns,
            "sequence": hash_sequence(seq), "code": code_version(), "plane_check_height": camera_height}


def _reuse(seq: Sequence, out: Path, stamp: dict) -> bool:
    """Point ``seq``'s views at an earlier run's label PNGs under ``out`` when its stamp matches."""
    from pavemap.segment.labels import PRESETS

    f = out / STAMP
    try:
        if json.loads(f.read_text()) != stamp:
            return False
    except (OSError, ValueError):
        return False
    paths = {(fr.index, cam): out / f"semantics/{cam}/{fr.index:06d}.png" for fr in seq.frames for cam in fr.views}
    if not all(p.is_file() for p in paths.values()):
        return False
    for fr in seq.frames:
        for cam, v in fr.views.items():
            v.semantics = str(paths[(fr.index, cam)].resolve())
    seq.classes = list(PRESETS["cityscapes"]().classes)
    return True


def semantics_for_run(seq: Sequence, spec: str, weights: str | os.PathLike | None, device: str,
                      out: Path, camera_height: float | None = None) -> tuple[Sequence, str]:
    """A drive without semantic maps gets the segmenter's, written under the run folder ``out`` (the sequence
    folder is not touched); returns the sequence to run on (a copy when labelled) and what was done.

    ``spec`` ``auto``: missing weights or grey images fall back to running without semantics (said in the
    returned text and a warning); ``espnet`` / ``espnetv2``: they are errors; ``none``: no segmenter.
    ``camera_height``: the run's camera-height prior, for the plane check of the road mask.
    """
    if spec not in CHOICES:
        raise PavemapError(f"--segmenter {spec!r}: choose {', '.join(CHOICES)}")
    if has_semantics(seq):
        return seq, "semantic maps of the sequence"
    if spec == "none":
        return seq, "none (--segmenter none)"
    arch = arch_of(spec)
    try:
        check_colour(seq)
        path = find_weights(arch, weights)
    except PavemapError as e:
        if spec != "auto":
            raise
        msg = f"no semantic maps and no segmenter: {e} -> running without semantics (mesh footprint as road)"
        log.warning("%s", msg)
        return seq, "none (" + ("grey images" if isinstance(e, GreyImagesError) else "segmenter weights missing") + ")"
    seq = copy.deepcopy(seq)
    stamp = _stamp(seq, arch, path, camera_height)
    if _reuse(seq, out, stamp):
        return seq, f"{arch} segmenter ({path}), reused from {out / 'semantics'}"
    log.info("no semantic maps: segmenting with %s (%s)", arch, path)
    seq = espnet_semantics(seq, arch, path, device, out_root=out, camera_height=camera_height)
    atomic_write_json(out / STAMP, stamp)  # after the labels: a stamp never vouches for half a set
    return seq, f"{arch} segmenter ({path})"
