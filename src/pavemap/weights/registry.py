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
import shutil
from dataclasses import dataclass
from pathlib import Path

from pavemap.errors import PavemapError
from pavemap.io.atomic import atomic_path
from pavemap.user_cache import install_dir, weight_dirs

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


KNOWN: tuple[KnownWeights, ...] = (
    KnownWeights(SHIPPED_WEIGHTS, "53d3ca8ebfeb2c3ee6e91d31ec0ba011a728066beec43a856bd3e0c34192c818", "detector",
                 "default road-defect detector (YOLOv5n, RDD2022; ships in the package)", required=True),
    KnownWeights("espnetv2_s_2.0_city_1024x512.pth",
                 "a72d59699801c7ce8e8b89a53af9097eaaa60dc12180ecde86fd700ba1222fe8", "segmenter",
                 "ESPNetv2 Cityscapes segmenter (sacmehta/EdgeNets; optional)", folder="espnetv2-cityscapes"),
    KnownWeights("espnet_p_2_q_8.pth", "343b0e77e8545d36113c4f3efbf1ee349256f25c97c9f9d5ddefe45f2f49763e",
                 "segmenter", "ESPNet Cityscapes segmenter (sacmehta/ESPNet; optional)", folder="espnet-cityscapes"),
)


def known(file: str) -> KnownWeights | None:
    """The registry entry of a file name, or None."""
    return next((k for k in KNOWN if k.file == file), None)


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
        from pavemap.segment.espnet import weight_dirs as seg_dirs

        dirs = seg_dirs()
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


def weight_rows() -> list[dict]:
    """One row per known file found (every place it is found), and one per known file found nowhere:
    {file, kind, what, required, where, path, size, sha256, expected, ok}; ``ok`` None when not found."""
    rows = []
    for k in KNOWN:
        seen: set[Path] = set()
        for where, p in candidates(k):
            if p in seen or not p.is_file():
                continue
            seen.add(p)
            digest = sha256_of(p)
            rows.append({"file": k.file, "kind": k.kind, "what": k.what, "required": k.required, "where": where,
                         "path": p, "size": p.stat().st_size, "sha256": digest, "expected": k.sha256,
                         "ok": digest == k.sha256})
        if not seen:
            rows.append({"file": k.file, "kind": k.kind, "what": k.what, "required": k.required, "where": "",
                         "path": None, "size": None, "sha256": None, "expected": k.sha256, "ok": None})
    return rows


def verify_problems(rows: list[dict] | None = None) -> list[str]:
    """One line per problem: a known file whose sha256 differs from the registry's, a required one missing."""
    problems = []
    for r in weight_rows() if rows is None else rows:
        if r["ok"] is False:
            problems.append(f"{r['path']}: sha256 {r['sha256']} differs from the expected {r['expected']} "
                            f"({r['file']}: a damaged or different file)")
        elif r["ok"] is None and r["required"]:
            looked = ", ".join(str(p) for _, p in candidates(known(r["file"])))  # type: ignore[arg-type]
            problems.append(f"{r['file']}: missing (looked in {looked}); reinstall pavemap or "
                            f"`pavemap weights install {r['file']}`")
    return problems


def check_yolo_checkpoint(path: Path) -> str:
    """Raise PavemapError unless ``path`` is a YOLO detection checkpoint; returns its class names.

    Read first without running anything from the file (an allow-list unpickler), then by ultralytics.
    """
    from pavemap.detect.pretrained import inert_load

    try:
        ckpt = inert_load(path, foreign=("ultralytics.",))
    except PavemapError:
        raise
    except Exception as e:  # noqa: BLE001 - a damaged pickle fails in many ways; one line naming the file
        raise PavemapError(f"{path}: not a loadable YOLO checkpoint ({type(e).__name__}: {e})") from None
    if not isinstance(ckpt, dict) or (ckpt.get("ema") or ckpt.get("model")) is None:
        raise PavemapError(f"{path}: not a YOLO checkpoint (no 'model' entry)")
    from pavemap.detect.yolo import load_detector

    model = load_detector(path)  # the globals were checked above: only torch / ultralytics classes
    return ", ".join(str(v) for v in model.names.values())


def _check_segmenter(path: Path, entry: KnownWeights) -> str:
    """Raise PavemapError unless ``path`` is a plain state dict of tensors (read with weights_only=True)."""
    from pavemap.segment.espnet import _state_dict

    sd = _state_dict(path)
    return f"{len(sd)} tensors ({entry.what})"


def install_weights(src: str | os.PathLike, dest_dir: Path | None = None, force: bool = False) -> tuple[Path, str]:
    """Copy ``src`` into the user's weight folder (atomically) after checking it loads; returns (path, summary).

    A file named like a known segmenter must be a state dict of tensors; any other file must be a YOLO
    detection checkpoint (``.pt``). An existing different file of the same name is kept unless ``force``.
    """
    p = Path(src).expanduser()
    if not p.is_file():
        raise PavemapError(f"{p}: file not found")
    entry = known(p.name)
    if entry is not None and entry.kind == "segmenter":
        summary = _check_segmenter(p, entry)
    else:
        if p.suffix.lower() != ".pt":
            raise PavemapError(f"{p}: expected a YOLO detection checkpoint (.pt), got {p.suffix or 'no suffix'}")
        summary = f"YOLO detector, classes {check_yolo_checkpoint(p)}"
    dest = (dest_dir or install_dir()) / p.name
    if dest.resolve() == p.resolve():
        return dest, summary + " (already in place)"
    if dest.exists() and not force and sha256_of(dest) != sha256_of(p):
        raise PavemapError(f"{dest}: a different file of that name is installed; pass --force to replace it")
    with atomic_path(dest) as tmp:
        shutil.copyfile(p, tmp)
    digest = sha256_of(dest)
    if entry is not None and digest != entry.sha256:
        summary += f"; note: sha256 {digest[:12]}… is not the published {entry.file}'s"
    return dest, summary


__all__ = ["KNOWN", "SHIPPED_WEIGHTS", "KnownWeights", "candidates", "check_yolo_checkpoint", "install_weights",
           "known", "packaged_path", "sha256_of", "verify_problems", "weight_rows"]
