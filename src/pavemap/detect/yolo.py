"""ultralytics YOLO backend: detection on a sequence, and detector training.

Offline by construction: :func:`_import_ultralytics` prepares a project-local config
folder with a local font (``pavemap.assets``), sets ``YOLO_OFFLINE=1``, makes
torchvision importable on CPU-only torch (``pavemap.detect.compat``) and only then
imports ultralytics. Weights are always a path to an existing file: a bare name like
``yolov8n.pt`` would make ultralytics download it, so it is refused with a clear error.
Training starts from a model *yaml* (random init) or a local ``.pt``.
"""

from __future__ import annotations

import logging
import os
import sys
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import torch

from pavemap.errors import PavemapError
from pavemap.io.sequence import load_rgb, write_detections
from pavemap.types import DEFECT_CODES, Detection, Sequence
from pavemap.weights.registry import sha256_of

log = logging.getLogger(__name__)

WEIGHT_SUFFIXES = (".pt",)


def ultralytics_device_of(device: str | None = "auto") -> str:
    """A pavemap ``--device`` in ultralytics' spelling, through the one resolver (:mod:`pavemap.device`)."""
    from pavemap.device import resolve_device, ultralytics_device

    return ultralytics_device(resolve_device(device))


def _import_ultralytics():
    """Import ultralytics offline (env, font, torchvision shim first); returns the module."""
    if "ultralytics" not in sys.modules:
        from pavemap.assets import prepare_ultralytics
        from pavemap.detect.compat import ensure_torchvision

        prepare_ultralytics()
        ensure_torchvision()
    try:
        import ultralytics
        import ultralytics.utils.patches as ul_patches
    except ImportError as e:
        raise PavemapError(
            f"the YOLO backend needs ultralytics: pip install 'pavemap[yolo]' (ultralytics-opencv-headless) ({e})"
        ) from None
    # ultralytics replaces PIL.Image.open process-wide with a wrapper that, on an unreadable file,
    # tries to install pi-heif; pavemap reports unreadable images itself, offline: undo it.
    from PIL import Image

    Image.open = getattr(ul_patches, "_image_open", Image.open)
    # ultralytics logs every prediction at INFO; pavemap reports its own progress
    logging.getLogger("ultralytics").setLevel(logging.WARNING)
    return ultralytics


def _check_weights_path(weights: str | os.PathLike) -> Path:
    p = Path(weights)
    if not p.is_file():
        hint = (
            " (pavemap never downloads weights: put a YOLO detection .pt file there, e.g. "
            "the shipped one (pavemap.detect.backends.shipped_weights()), or train one with "
            "`pavemap train-detector`)"
        )
        if p.parent == Path(".") and p.suffix == ".pt":
            raise PavemapError(f"weights file {str(p)!r} not found in {Path.cwd()}{hint}")
        raise PavemapError(f"weights file {p} not found{hint}")
    if p.suffix.lower() not in WEIGHT_SUFFIXES:
        raise PavemapError(f"{p}: expected a PyTorch YOLO weights file (.pt), got {p.suffix or 'no suffix'}")
    return p


def load_detector(weights: str | os.PathLike):
    """Load a YOLO *detection* model from a local ``.pt``; wrong task or unreadable file → PavemapError."""
    p = _check_weights_path(weights)
    _import_ultralytics()
    from ultralytics import YOLO

    try:
        model = YOLO(str(p.resolve()))
    except Exception as e:  # ultralytics raises many types for a bad checkpoint; report one line
        raise PavemapError(f"{p}: cannot load YOLO weights ({type(e).__name__}: {e})") from None
    task = getattr(model, "task", None)
    if task != "detect":
        raise PavemapError(
            f"{p}: these are YOLO '{task}' weights; the detector needs 'detect' weights "
            "(boxes of D00/D10/D20/D40 road defects, e.g. trained on RDD2022)"
        )
    return model


def _batches(items: list, size: int) -> Iterator[list]:
    for i in range(0, len(items), size):
        yield items[i : i + size]


def detect_sequence(
    seq: Sequence,
    weights: str | os.PathLike,
    out: str | os.PathLike,
    imgsz: int = 800,
    conf: float = 0.05,
    device: str = "auto",
    batch: int = 8,
    class_map: str | os.PathLike | None = None,
    iou: float = 0.5,
    progress: bool = True,
) -> int:
    """Run a YOLO detection model over every view of ``seq``; write ``out`` (detections.jsonl); a progress bar
    on a terminal when ``progress``.

    Boxes come back in full-resolution pixels of each original image (ultralytics
    undoes its letterbox). Model classes are mapped by name to D00/D10/D20/D40
    (:mod:`pavemap.detect.classmap`, override with ``class_map`` YAML); unmapped classes
    are dropped. Returns the number of detections written.
    """
    from tqdm import tqdm

    from pavemap.detect.classmap import build_class_map, load_class_map

    if batch < 1 or imgsz < 32:
        raise PavemapError(f"batch must be >= 1 and imgsz >= 32 (got batch={batch}, imgsz={imgsz})")
    if not 0.0 <= conf < 1.0:
        raise PavemapError(f"conf must be in [0, 1), got {conf}")
    overrides = load_class_map(class_map) if class_map is not None else None
    model = load_detector(weights)
    model_sha = sha256_of(weights)  # each line names its model: `pavemap fuse` finds the weights' operating point
    lut, dropped = build_class_map(model.names, overrides)
    if dropped:
        log.info("YOLO classes not mapped to D00/D10/D20/D40 are dropped: %s", ", ".join(dropped))
    dev = ultralytics_device_of(device)

    views = [(f.index, cam, v) for f in seq.frames for cam, v in f.views.items()]
    dets: list[Detection] = []
    extra: list[dict] = []
    n_dropped = 0
    with tqdm(total=len(views), desc="yolo detect", unit="img", disable=None if progress else True) as bar:
        for chunk in _batches(views, batch):
            # ultralytics wants BGR arrays; reading ourselves gives clear errors on bad files
            imgs = [np.ascontiguousarray(load_rgb(seq.path(v.image))[:, :, ::-1]) for _, _, v in chunk]
            results = model.predict(
                imgs, imgsz=imgsz, conf=conf, iou=iou, device=dev, batch=len(imgs), verbose=False
            )
            for (frame, cam, _), r in zip(chunk, results, strict=True):
                if r.boxes is None or len(r.boxes) == 0:
                    continue
                xyxy = r.boxes.xyxy.detach().cpu().numpy().astype(np.float64)  # (N, 4) original pixels
                mcls = r.boxes.cls.detach().cpu().numpy().astype(np.int64)  # (N,)
                scores = r.boxes.conf.detach().cpu().numpy().astype(np.float64)  # (N,)
                h, w = r.orig_shape
                xyxy[:, [0, 2]] = np.clip(xyxy[:, [0, 2]], 0, w)
                xyxy[:, [1, 3]] = np.clip(xyxy[:, [1, 3]], 0, h)
                ours = np.where((mcls >= 0) & (mcls < len(lut)), lut[np.clip(mcls, 0, len(lut) - 1)], -1)
                keep = ours >= 0
                n_dropped += int((~keep).sum())
                for b, c, s, mc in zip(xyxy[keep], ours[keep], scores[keep], mcls[keep], strict=True):
                    dets.append(Detection(frame, cam, tuple(float(x) for x in b), int(c), float(s)))
                    extra.append({"model_cls": str(model.names.get(int(mc), mc)), "model": model_sha})
            bar.update(len(chunk))
    write_detections(out, dets, extra)
    if n_dropped:
        log.info("dropped %d detections of unmapped classes", n_dropped)
    return len(dets)


# ----------------------------------------------------------------------------- training


def _offline_amp_check(model) -> bool:  # noqa: ARG001 - same signature as ultralytics' check_amp
    """ultralytics' AMP check downloads yolo26n.pt to compare outputs; pavemap stays offline.

    AMP is used on CUDA (PyTorch's autocast is well tested on current GPUs); elsewhere off.
    """
    return torch.cuda.is_available()


def resolve_data_yaml(data: str | os.PathLike, workdir: str | os.PathLike) -> Path:
    """Check an ultralytics dataset yaml and write a copy whose ``path`` is absolute.

    ultralytics resolves a relative ``path:`` against the *current directory* (or its
    datasets folder), not the yaml's folder; users (and RDD2022 conversions) mean the
    yaml's folder. Missing train/val folders and names → PavemapError naming the file.
    """
    import yaml

    from pavemap.io.atomic import atomic_write_text

    data = Path(data)
    if not data.is_file():
        raise PavemapError(f"dataset file {data} not found (an ultralytics data yaml: path, train, val, names)")
    from pavemap.io.yamlfile import read_yaml

    d = read_yaml(data, "dataset yaml")
    if not isinstance(d, dict):
        raise PavemapError(f"{data}: a dataset yaml must be a mapping with path, train, val, names")
    missing = [k for k in ("train", "val", "names") if k not in d]
    if missing:
        raise PavemapError(f"{data}: missing key(s) {', '.join(missing)}")
    root = Path(d.get("path") or ".")
    if not root.is_absolute():
        root = (data.parent / root).resolve()
    for split in ("train", "val"):
        for rel in d[split] if isinstance(d[split], list) else [d[split]]:
            if not (root / rel).exists():
                raise PavemapError(f"{data}: {split} folder {root / rel} does not exist")
    d["path"] = str(root)
    out = Path(workdir) / f"{data.stem}.resolved.yaml"
    atomic_write_text(out, yaml.safe_dump(d, sort_keys=False))
    return out


def train_detector(
    data: str | os.PathLike,
    model: str = "yolov8n.yaml",
    epochs: int = 100,
    imgsz: int = 640,
    device: str = "auto",
    batch: int = 16,
    project: str | os.PathLike = "runs/detect",
    name: str = "train",
    time_hours: float | None = None,
    workers: int = 8,
    cache: str | bool = False,
    plots: bool = False,
    resume: str | os.PathLike | None = None,
    **kwargs,
) -> Path:
    """Train a YOLO detector (ultralytics) offline; returns the path of ``best.pt``.

    ``model`` is a model yaml known to ultralytics (``yolov8n.yaml``, ``yolo11n.yaml``;
    random init, nothing downloaded) or a local ``.pt`` to fine-tune. ``data`` is an
    ultralytics dataset yaml whose class names should be D00/D10/D20/D40 (or be mapped
    at detection time with a class map). ``time_hours`` bounds the run by wall time
    (ultralytics re-plans the epochs and the LR schedule to fit). ``resume`` continues
    from a ``last.pt``.
    """
    if resume is None and not str(model).endswith((".yaml", ".yml")):
        _check_weights_path(model)
    _import_ultralytics()
    import ultralytics.engine.trainer as trainer_mod
    from ultralytics import YOLO

    trainer_mod.check_amp = _offline_amp_check
    logging.getLogger("ultralytics").setLevel(logging.INFO)  # training progress is worth seeing
    if resume is not None:
        yolo = YOLO(str(_check_weights_path(resume)))
        results = yolo.train(resume=True)
    else:
        run_dir = Path(project).resolve() / name
        data_file = resolve_data_yaml(data, run_dir)
        yolo = YOLO(str(model))
        if yolo.task != "detect":
            raise PavemapError(f"{model}: a '{yolo.task}' model; train-detector needs a detection model")
        args = dict(
            data=str(data_file),
            epochs=epochs,
            imgsz=imgsz,
            device=ultralytics_device_of(device),
            batch=batch,
            project=str(Path(project).resolve()),
            name=name,
            exist_ok=True,
            pretrained=not str(model).endswith((".yaml", ".yml")),
            workers=workers,
            cache=cache,
            plots=plots,
            verbose=True,
        )
        if time_hours:
            args["time"] = float(time_hours)
        args.update(kwargs)
        results = yolo.train(**args)
    save_dir = Path(getattr(results, "save_dir", None) or yolo.trainer.save_dir)
    best = save_dir / "weights" / "best.pt"
    if not best.is_file():
        best = save_dir / "weights" / "last.pt"
    return best


__all__ = ["DEFECT_CODES", "detect_sequence", "load_detector", "train_detector", "ultralytics_device_of"]
