"""Run configuration: presets carrying the paper's parameters and a validated YAML schema.

A config file is YAML with optional sections ``mesh``, ``detector``, ``fusion``, ``output``
and top-level ``preset`` and ``device``::

    preset: nuscenes        # start from a preset, then override
    device: auto
    mesh:      {epochs: 7, resolution: 0.1}
    detector:  {backend: sim, seed: 0}
    fusion:    {association: hit, tau_road: 0.5}
    output:    {overlay_frames: 3}

The keys of ``mesh`` and ``fusion`` are the fields of :class:`pavemap.mesh.MeshConfig` and
:class:`pavemap.fuse.FusionConfig`, so the schema can never drift from the code. An
unknown key is an error naming the key and the nearest valid one.
"""

from __future__ import annotations

import dataclasses
import difflib
import os
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from pavemap.errors import PavemapError

PRESETS = ("nuscenes", "kitti")


@dataclass
class DetectorConfig:
    backend: str = "sim"  # sim | yolo | file
    weights: str | None = None  # yolo: path to detection weights (.pt)
    file: str | None = None  # file: detections JSONL or a folder of YOLO txt files
    seed: int = 0  # sim: random seed
    imgsz: int = 640
    conf: float = 0.01  # yolo: keep everything above this; the fusion threshold decides later
    batch: int = 8
    class_map: str | None = None


@dataclass
class OutputConfig:
    figures: bool = True
    report: bool = True
    overlay_frames: int = 3
    sweep_tau_conf: tuple[float, ...] = (0.05, 0.10, 0.15, 0.20, 0.25, 0.35, 0.5)


@dataclass
class RunConfig:
    preset: str = "nuscenes"
    device: str = "auto"
    mesh: Any = None  # pavemap.mesh.MeshConfig
    detector: DetectorConfig = field(default_factory=DetectorConfig)
    fusion: Any = None  # pavemap.fuse.FusionConfig
    output: OutputConfig = field(default_factory=OutputConfig)

    def to_dict(self) -> dict:
        return _to_plain(dataclasses.asdict(self))


def _to_plain(o: Any) -> Any:
    if isinstance(o, dict):
        return {k: _to_plain(v) for k, v in o.items()}
    if isinstance(o, list | tuple):
        return [_to_plain(v) for v in o]
    if isinstance(o, Path):
        return str(o)
    return o


def _section_classes() -> dict[str, type]:
    from pavemap.fuse import FusionConfig
    from pavemap.mesh import MeshConfig

    return {"mesh": MeshConfig, "detector": DetectorConfig, "fusion": FusionConfig, "output": OutputConfig}


def preset_config(name: str) -> RunConfig:
    """The paper's parameters (SPEC, its Table 2) for ``nuscenes`` or ``kitti``."""
    if name not in PRESETS:
        raise PavemapError(f"unknown preset {name!r}; choose one of {', '.join(PRESETS)} or a .yaml file")
    classes = _section_classes()
    return RunConfig(
        preset=name,
        mesh=classes["mesh"].preset(name),
        fusion=classes["fusion"].preset(name),
    )


def preset_for(seq: object) -> tuple[str, str]:
    """The preset that fits a sequence's rig, and why: one camera → ``kitti``, a surround rig → ``nuscenes``.

    The paper's two parameter sets differ by rig (crop 5 m vs 7 m, L = 4 vs 5, τ_conf 0.10 vs 0.05), so
    a front-camera drive run with the surround preset would silently get the wider crop.
    """
    cams = getattr(seq, "cameras", {}) or {}
    n = len(cams)
    if n <= 1:
        return "kitti", f"{n} camera: a single front camera, so the kitti preset"
    return "nuscenes", f"{n} cameras: a surround rig, so the nuscenes preset"


def _unknown_key(key: str, valid: typing.Iterable[str], where: str, file: str) -> PavemapError:
    valid = sorted(valid)
    near = difflib.get_close_matches(key, valid, n=1, cutoff=0.5)
    hint = f"; did you mean {near[0]!r}?" if near else f"; valid keys: {', '.join(valid)}"
    return PavemapError(f"{file}: unknown key {key!r} in {where}{hint}")


def _coerce(value: Any, current: Any, key: str, where: str, file: str) -> Any:
    """Check a YAML value against the type of the default it replaces."""
    if current is None or value is None:
        return value
    if isinstance(current, bool):
        if not isinstance(value, bool):
            raise PavemapError(f"{file}: {where}.{key} must be true or false, got {value!r}")
        return value
    if isinstance(current, int | float) and not isinstance(current, bool):
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise PavemapError(f"{file}: {where}.{key} must be a number, got {value!r}")
        return type(current)(value) if isinstance(current, float) or float(value).is_integer() else value
    if isinstance(current, str):
        if not isinstance(value, str):
            raise PavemapError(f"{file}: {where}.{key} must be a string, got {value!r}")
        return value
    if isinstance(current, tuple | list):
        if not isinstance(value, list | tuple):
            raise PavemapError(f"{file}: {where}.{key} must be a list, got {value!r}")
        return tuple(value) if isinstance(current, tuple) else list(value)
    return value


def apply_overrides(cfg: RunConfig, data: dict, file: str = "<config>") -> RunConfig:
    """Apply a parsed YAML mapping onto ``cfg``; unknown keys and wrong types raise PavemapError."""
    if not isinstance(data, dict):
        raise PavemapError(f"{file}: top level must be a mapping of sections")
    top = {"preset", "device", "mesh", "detector", "fusion", "output"}
    for key in data:
        if key not in top:
            raise _unknown_key(key, top, "the top level", file)
    if "device" in data:
        cfg.device = str(data["device"])
    for section in ("mesh", "detector", "fusion", "output"):
        values = data.get(section)
        if values is None:
            continue
        if not isinstance(values, dict):
            raise PavemapError(f"{file}: section {section!r} must be a mapping")
        obj = getattr(cfg, section)
        names = {f.name for f in dataclasses.fields(obj)}
        for key, value in values.items():
            if key not in names:
                raise _unknown_key(key, names, f"section {section!r}", file)
            setattr(obj, key, _coerce(value, getattr(obj, key), key, section, file))
    if cfg.detector.backend not in ("sim", "yolo", "file"):
        raise PavemapError(f"{file}: detector.backend must be sim, yolo or file, got {cfg.detector.backend!r}")
    return cfg


def load_config(spec: str | os.PathLike | None, default_preset: str = "nuscenes") -> RunConfig:
    """Resolve ``--config``: a preset name, a YAML file (optionally naming a base ``preset``), or None."""
    if spec is None:
        return preset_config(default_preset)
    spec = str(spec)
    if spec in PRESETS:
        return preset_config(spec)
    path = Path(spec)
    if not path.is_file():
        raise PavemapError(f"config {spec!r} is neither a preset ({', '.join(PRESETS)}) nor an existing YAML file")
    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8")) or {}
    except yaml.YAMLError as e:
        raise PavemapError(f"{path}: invalid YAML ({e})") from None
    if not isinstance(data, dict):
        raise PavemapError(f"{path}: top level must be a mapping of sections")
    base = data.get("preset", default_preset)
    if base not in PRESETS:
        raise PavemapError(f"{path}: preset must be one of {', '.join(PRESETS)}, got {base!r}")
    return apply_overrides(preset_config(base), data, str(path))


def dump_config(cfg: RunConfig) -> str:
    return yaml.safe_dump(cfg.to_dict(), sort_keys=False)
