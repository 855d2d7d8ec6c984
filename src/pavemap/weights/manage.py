"""Listing, verifying and installing weight files (``pavemap weights``): the checks behind the command.

The table of known files and where they are searched is :mod:`pavemap.weights.registry`; this module loads
candidate files (through the detector's and the segmenter's own loaders), so it sits with the commands.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

from pavemap.errors import PavemapError
from pavemap.io.atomic import atomic_path
from pavemap.user_cache import install_dir
from pavemap.weights.registry import KNOWN, KnownWeights, candidates, known, sha256_of


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


__all__ = ["check_yolo_checkpoint", "install_weights", "verify_problems", "weight_rows"]
