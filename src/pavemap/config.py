"""Run configuration: presets carrying the paper's parameters, and one schema derived from the types.

A config file is YAML with optional sections ``mesh``, ``detector``, ``filter``, ``fusion``,
``maintenance``, ``output`` and top-level ``preset``, ``device`` and ``skip_bad_frames``::

    preset: nuscenes        # start from a preset, then override
    device: auto
    skip_bad_frames: false  # true: frames with a damaged file are dropped with a warning (docs/faults.md)
    mesh:      {epochs: 2, resolution: 0.1}
    detector:  {backend: auto, seed: 0}
    filter:    {tau_conf: 0.05, tau_road: 0.5, mask: frame}
    fusion:    {association: hit}
    maintenance: {policy: "", segment_m: 100}
    output:    {overlay_frames: 3}

The keys of a section are the fields of its dataclass (:class:`pavemap.mesh.MeshConfig`,
:class:`pavemap.detect.config.DetectorConfig`, :class:`pavemap.detect.config.FilterConfig`,
:class:`pavemap.fuse.FusionConfig`, :class:`pavemap.maintain.MaintenanceConfig`, :class:`OutputConfig`)
and a value is checked against the field's type hint (:func:`coerce`), so the schema cannot drift from the
code. The same check turns command-line text (``--set fusion.hit_radius_m=0.4``) into typed values. After the
values are in, every section's ``validate()`` range-checks it, so a bad value stops the run before any stage starts.
"""

from __future__ import annotations

import dataclasses
import difflib
import functools
import math
import os
import re
import sys
import typing
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import yaml

from pavemap.detect.config import DetectorConfig, FilterConfig
from pavemap.device import CHOICES as DEVICE_CHOICES
from pavemap.device import is_device_name
from pavemap.errors import PavemapError
from pavemap.io.yamlfile import read_yaml
from pavemap.maintain.config import MaintenanceConfig
from pavemap.typed_values import coerce

if TYPE_CHECKING:  # the stage configs import torch through their packages: loaded on first use
    from pavemap.fuse.config import FusionConfig
    from pavemap.mesh.config import MeshConfig

Preset = Literal["nuscenes", "kitti"]
PRESETS: tuple[str, ...] = typing.get_args(Preset)
SECTIONS: tuple[str, ...] = ("mesh", "detector", "filter", "fusion", "maintenance", "output")
TOP_LEVEL: tuple[str, ...] = ("preset", "device", "skip_bad_frames")


@dataclass
class OutputConfig:
    """What ``pavemap run`` writes besides the defect map.

    - ``figures`` / ``report``: the PNG figures and ``report.html``.
    - ``overlay_frames``: frames drawn with their detections in the report (0: none).
    - ``sweep_tau_conf``: confidence thresholds of the report's precision/recall sweep, each in [0, 1].
    - ``crs``: CRS of the GeoTIFF and the GIS layers of a georeferenced run: ``auto`` (the drive's UTM
      zone) or a projected CRS such as ``EPSG:25832`` (``--crs``).
    - ``extra_formats``: GIS files besides ``survey.gpkg``: ``fgb`` (FlatGeobuf), ``kml``, ``kmz``.
    - ``vehicle``: free text for the ``survey`` layer (e.g. the vehicle's plate or fleet number).
    """

    figures: bool = True
    report: bool = True
    overlay_frames: int = 3
    sweep_tau_conf: tuple[float, ...] = (0.05, 0.10, 0.15, 0.20, 0.25, 0.35, 0.5)
    crs: str = "auto"
    extra_formats: tuple[Literal["fgb", "kml", "kmz"], ...] = ()
    vehicle: str = ""

    def validate(self) -> None:
        """Raise PavemapError naming the first bad field."""
        if self.overlay_frames < 0:
            raise PavemapError(f"output.overlay_frames must be >= 0, got {self.overlay_frames}")
        if not self.sweep_tau_conf:
            raise PavemapError("output.sweep_tau_conf needs at least one threshold")
        for t in self.sweep_tau_conf:
            if not (math.isfinite(t) and 0.0 <= t <= 1.0):
                raise PavemapError(f"output.sweep_tau_conf values must be in [0, 1], got {t}")
        from pavemap.geo.crs import check_crs_setting

        check_crs_setting(self.crs, "output.crs")


def _section_types() -> dict[str, type]:
    from pavemap.fuse.config import FusionConfig
    from pavemap.mesh.config import MeshConfig

    return {"mesh": MeshConfig, "detector": DetectorConfig, "filter": FilterConfig, "fusion": FusionConfig,
            "maintenance": MaintenanceConfig, "output": OutputConfig}


def _section_for(section: str, preset: str) -> object:
    cls = _section_types()[section]
    return cls.preset(preset) if hasattr(cls, "preset") else cls()


@dataclass
class RunConfig:
    """Everything ``pavemap run`` needs; a section per stage, each a typed dataclass with ``validate()``."""

    preset: Preset = "nuscenes"
    device: str = "auto"
    skip_bad_frames: bool = False  # drop frames whose files do not decode (else such a frame is an error)
    mesh: MeshConfig = field(default_factory=lambda: _section_for("mesh", "nuscenes"))
    detector: DetectorConfig = field(default_factory=DetectorConfig)
    filter: FilterConfig = field(default_factory=lambda: FilterConfig.preset("nuscenes"))
    fusion: FusionConfig = field(default_factory=lambda: _section_for("fusion", "nuscenes"))
    maintenance: MaintenanceConfig = field(default_factory=MaintenanceConfig)
    output: OutputConfig = field(default_factory=OutputConfig)

    def to_dict(self) -> dict:
        return _to_plain(dataclasses.asdict(self))

    def validate(self) -> None:
        """Range-check every section; raise PavemapError naming ``section.field``."""
        if self.preset not in PRESETS:
            raise PavemapError(f"preset must be one of {', '.join(PRESETS)}, got {self.preset!r}")
        if not is_device_name(self.device):
            raise PavemapError(f"device must be {DEVICE_CHOICES}, got {self.device!r}")
        for section in SECTIONS:
            getattr(self, section).validate()


def _to_plain(o: Any) -> Any:
    if isinstance(o, dict):
        return {k: _to_plain(v) for k, v in o.items()}
    if isinstance(o, list | tuple):
        return [_to_plain(v) for v in o]
    if isinstance(o, Path):
        return str(o)
    return o


@functools.cache
def field_types(cls: type) -> dict[str, Any]:
    """``{field: type hint}`` of a config dataclass (string annotations resolved)."""
    module = sys.modules[cls.__module__]
    local = {c.__name__: c for c in _section_types().values()} if cls is RunConfig else None
    hints = typing.get_type_hints(cls, globalns=vars(module), localns=local)
    return {f.name: hints[f.name] for f in dataclasses.fields(cls)}


def field_names() -> list[str]:
    """Every key ``--set`` accepts: ``device``, ``skip_bad_frames`` and ``section.field`` for each section field."""
    types_ = _section_types()
    return ["device", "skip_bad_frames"] + [f"{s}.{f.name}" for s in SECTIONS for f in dataclasses.fields(types_[s])]


# ---------------------------------------------------------------------------- applying values


def _unknown_key(key: str, valid: Iterable[str], where: str, source: str,
                 elsewhere: Iterable[str] = ()) -> PavemapError:
    valid = sorted(valid)
    moved = [k for k in elsewhere if k.rpartition(".")[2] == key]
    near = moved or difflib.get_close_matches(key, valid, n=1, cutoff=0.5)
    hint = f"; did you mean {near[0]!r}?" if near else f"; valid keys: {', '.join(valid)}"
    return PavemapError(f"{source}: unknown key {key!r} in {where}{hint}")


def _set_field(obj: object, section: str, key: str, value: Any, source: str, text: bool) -> None:
    hints = field_types(type(obj))
    if key not in hints:
        others = [k for k in field_names() if not k.startswith(f"{section}.")]
        raise _unknown_key(key, hints, f"section {section!r}", source, others)
    setattr(obj, key, coerce(value, hints[key], f"{section}.{key}", source, text))


def _set_top(cfg: RunConfig, key: str, value: Any, source: str, text: bool) -> None:
    setattr(cfg, key, coerce(value, field_types(RunConfig)[key], key, source, text))


def _validated(cfg: RunConfig, source: str) -> RunConfig:
    try:
        cfg.validate()
    except PavemapError as e:
        raise PavemapError(f"{source}: {e}") from None
    return cfg


def apply_overrides(cfg: RunConfig, data: dict, file: str = "<config>") -> RunConfig:
    """Apply a parsed YAML mapping onto ``cfg`` and validate it; unknown keys and wrong types raise PavemapError."""
    if not isinstance(data, dict):
        raise PavemapError(f"{file}: top level must be a mapping of sections")
    for key, value in data.items():
        if key in SECTIONS:
            if value is None:
                continue
            if not isinstance(value, dict):
                raise PavemapError(f"{file}: section {key!r} must be a mapping")
            for k, v in value.items():
                _set_field(getattr(cfg, key), key, str(k), v, file, text=False)
        elif key in TOP_LEVEL:
            _set_top(cfg, key, value, file, text=False)
        else:
            raise _unknown_key(str(key), (*TOP_LEVEL, *SECTIONS), "the top level", file)
    return _validated(cfg, file)


# Several pairs in one --set value: split where the next `section.field=` starts.
_NEXT_PAIR = re.compile(r"\s+(?=[A-Za-z_]\w*\.[A-Za-z_]\w*=)")


def parse_overrides(items: Iterable[str]) -> list[tuple[str, str]]:
    """``["fusion.tau_road=0.6 mesh.epochs=3", "device=cpu"]`` → ``[(key, text), ...]`` in order."""
    pairs = []
    for item in items:
        for part in _NEXT_PAIR.split(item.strip()):
            if not part:
                continue
            key, sep, value = part.partition("=")
            if not sep or not key.strip():
                raise PavemapError(f"--set {part!r}: expected section.field=value, e.g. fusion.hit_radius_m=0.4")
            pairs.append((key.strip(), value.strip()))
    return pairs


def apply_text_overrides(cfg: RunConfig, items: Iterable[str], source: str = "--set") -> RunConfig:
    """Apply command-line ``section.field=value`` overrides (:func:`parse_overrides`) and validate."""
    pairs = parse_overrides(items)
    for key, value in pairs:
        where = f"{source} {key}={value}"
        section, dot, name = key.partition(".")
        if not dot:
            if key == "preset":
                raise PavemapError(f"{where}: choose the preset with --config nuscenes|kitti")
            if key not in TOP_LEVEL:
                raise _unknown_key(key, field_names(), "the config", where, field_names())
            _set_top(cfg, key, value, where, text=True)
        elif section not in SECTIONS:
            raise _unknown_key(section, SECTIONS, "the config's sections", where)
        else:
            _set_field(getattr(cfg, section), section, name, value, where, text=True)
    return _validated(cfg, source) if pairs else cfg


# ---------------------------------------------------------------------------- presets and files


def preset_config(name: str) -> RunConfig:
    """The paper's parameters (SPEC, its Table 2) for ``nuscenes`` or ``kitti``."""
    if name not in PRESETS:
        raise PavemapError(f"unknown preset {name!r}; choose one of {', '.join(PRESETS)} or a .yaml file")
    return RunConfig(preset=name, **{s: _section_for(s, name) for s in SECTIONS})  # type: ignore[arg-type]


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


def mount_height_prior(cfg: RunConfig, seq: object, spec: str | os.PathLike | None,
                       overrides: Iterable[str] = ()) -> str | None:
    """Set ``cfg.mesh.camera_height`` to the sequence's mount height (``Camera.height_m``: what an SfM import
    scaled the path to) unless an override or the YAML ``spec`` sets it; a rig only when its cameras agree within
    5 cm. Returns what was done, one line, or None when nothing changed."""
    heights = [c.height_m for c in (getattr(seq, "cameras", None) or {}).values() if c.height_m is not None]
    if (not heights or max(heights) - min(heights) > 0.05
            or any(str(o).split("=", 1)[0].strip() == "mesh.camera_height" for o in overrides)):
        return None
    if spec is not None and str(spec) not in PRESETS and Path(spec).is_file():
        data = read_yaml(Path(spec), "config") or {}
        if isinstance(data, dict) and "camera_height" in (data.get("mesh") or {}):
            return None
    h = float(sum(heights) / len(heights))
    if abs(h - cfg.mesh.camera_height) < 1e-6:
        return None
    before, cfg.mesh.camera_height = cfg.mesh.camera_height, h
    return (f"camera height prior {h:.2f} m from the sequence (the import's --camera-height; the preset says "
            f"{before:.2f} m; --set mesh.camera_height=... to change)")


def load_config(spec: str | os.PathLike | None, default_preset: str = "nuscenes",
                overrides: Iterable[str] = ()) -> RunConfig:
    """Resolve ``--config`` and ``--set``: a preset name, a YAML file (optionally naming a base ``preset``,
    else ``default_preset``) or None (``default_preset``), then ``section.field=value`` overrides.

    The result is validated: a bad key, type or range raises PavemapError naming the file and field.
    """
    if spec is None or str(spec) in PRESETS:
        cfg = _validated(preset_config(default_preset if spec is None else str(spec)), "preset")
    else:
        cfg = _load_yaml(Path(spec), default_preset)
    return apply_text_overrides(cfg, overrides)


def _load_yaml(path: Path, default_preset: str) -> RunConfig:
    if not path.is_file():
        raise PavemapError(f"config {str(path)!r} is neither a preset ({', '.join(PRESETS)}) nor an existing "
                           "YAML file")
    data = read_yaml(path, "config") or {}
    if not isinstance(data, dict):
        raise PavemapError(f"{path}: top level must be a mapping of sections")
    base = coerce(data.get("preset", default_preset), field_types(RunConfig)["preset"], "preset", str(path))
    return apply_overrides(preset_config(base), data, str(path))


def dump_config(cfg: RunConfig) -> str:
    return yaml.safe_dump(cfg.to_dict(), sort_keys=False)


__all__ = ["PRESETS", "SECTIONS", "DetectorConfig", "FilterConfig", "OutputConfig", "RunConfig", "apply_overrides",
           "apply_text_overrides", "coerce", "dump_config", "field_names", "field_types", "load_config",
           "mount_height_prior", "parse_overrides", "preset_config", "preset_for"]
