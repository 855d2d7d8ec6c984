"""The weight files pavemap knows, their expected sha256, where each is found, and installing one.

The expected hashes live here and nowhere else in code (the model card and docs quote them; a test
keeps the card in step). ``pavemap weights list / verify / install`` (:mod:`pavemap.commands.weights`)
is a thin layer over :func:`weight_rows`, :func:`verify_problems` and :func:`install_weights`.

Installing checks the file before copying it: a YOLO checkpoint is first read with an allow-list
unpickler (:func:`pavemap.detect.pretrained.inert_load`: torch and ultralytics classes become inert
stand-ins, anything else, e.g. ``os.system``, is refused) so a hostile pickle runs nothing; only then
does ultralytics load it for real to check it is a *detection* model. The copy is atomic
(:func:`pavemap.io.atomic.atomic_path`): a half-copied file never sits under the final name.
"""

from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass
from pathlib import Path

from pavemap.user_cache import weight_dirs, weight_search_dirs

#: the default detector's file name; it ships inside the package (``pavemap/weights/``, card beside it)
SHIPPED_WEIGHTS = "pavemap-yolov5n-rdd2022.pt"


@dataclass(frozen=True)
class KnownWeights:
    """One weight file pavemap knows by name: what it is for and its expected sha256."""

    file: str
    sha256: str
    kind: str  # "detector" (ultralytics YOLO checkpoint) or "segmenter" (plain state dict)
    what: str
    required: bool = False  # the default of a run: `pavemap weights verify` fails when it is missing
    folder: str = ""  # a sub-folder it may also sit in (shared/data/pretrained/<folder>/<file>)
    tau_conf: float | None = None  # a detector's measured operating point: the run's filter.tau_conf by default


KNOWN: tuple[KnownWeights, ...] = (
    KnownWeights(SHIPPED_WEIGHTS, "53d3ca8ebfeb2c3ee6e91d31ec0ba011a728066beec43a856bd3e0c34192c818", "detector",
                 "default road-defect detector (YOLOv5n, RDD2022; ships in the package)", required=True,
                 # the largest tau_conf whose F1 on the car-mounted Czech val is within 0.01 of the peak (0.405 vs
                 # 0.411 at 0.15) with 0.29 instead of 0.45 false boxes per clean frame; bench/results/detector.json
                 # operating_point_imgsz800 (tests/test_tau_conf.py keeps the two in step)
                 tau_conf=0.20),
    KnownWeights("espnetv2_s_2.0_city_1024x512.pth",
                 "a72d59699801c7ce8e8b89a53af9097eaaa60dc12180ecde86fd700ba1222fe8", "segmenter",
                 "ESPNetv2 Cityscapes segmenter (sacmehta/EdgeNets; optional)", folder="espnetv2-cityscapes"),
    KnownWeights("espnet_p_2_q_8.pth", "343b0e77e8545d36113c4f3efbf1ee349256f25c97c9f9d5ddefe45f2f49763e",
                 "segmenter", "ESPNet Cityscapes segmenter (sacmehta/ESPNet; optional)", folder="espnet-cityscapes"),
)


def known(file: str) -> KnownWeights | None:
    """The registry entry of a file name, or None."""
    return next((k for k in KNOWN if k.file == file), None)


def by_sha256(sha256: str) -> KnownWeights | None:
    """The registry entry whose file has this sha256 (or a prefix of it, >= 12 hex digits), or None."""
    sha = sha256.lower()
    if len(sha) < 12:
        return None
    return next((k for k in KNOWN if k.sha256.startswith(sha)), None)


def packaged_path(file: str = SHIPPED_WEIGHTS) -> Path:
    """Where ``file`` would sit inside the installed package (``pavemap/weights/``)."""
    from importlib.resources import files

    return Path(str(files("pavemap") / "weights" / file))


def candidates(entry: KnownWeights) -> list[tuple[str, Path]]:
    """(where, path) pairs searched for ``entry``, in order: the package (the shipped detector), the user's
    weight folders, and for a segmenter the folders its loader also searches."""
    out: list[tuple[str, Path]] = []
    user = weight_dirs()
    if entry.kind == "detector":
        out.append(("package", packaged_path(entry.file)))
        dirs = user
    else:
        dirs = weight_search_dirs()
    for d in dirs:
        where = "user" if d in user else "checkout"  # shared/data/pretrained beside a source checkout
        out.append((where, d / entry.file))
        if entry.folder:
            out.append((where, d / entry.folder / entry.file))
    return out


def sha256_of(path: str | os.PathLike, chunk: int = 1 << 20) -> str:
    """Hex sha256 of a file, read in 1 MiB chunks."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()


__all__ = ["KNOWN", "SHIPPED_WEIGHTS", "KnownWeights", "by_sha256", "candidates", "known", "packaged_path", "sha256_of"]
