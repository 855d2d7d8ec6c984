"""Options every command shares: one name, one help text and one code path per concept.

The config options (``--config``, ``--set`` and the shortcuts ``--device``, ``--epochs``, ``--detector`` …)
all end in :func:`resolve_config`, which turns the shortcuts into ``section.field=value`` overrides and
hands them to :func:`pavemap.config.load_config` together with ``--set``: a shortcut is only a shorter
spelling of a ``--set``, checked and validated the same way.
"""

from __future__ import annotations

import enum
import typing
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING

import typer

from pavemap.config import field_types
from pavemap.detect.config import DetectorConfig

if TYPE_CHECKING:
    from pavemap.config import RunConfig
    from pavemap.types import Sequence

DEVICE_HELP = "auto, cpu, cuda or cuda:N"


def literal_choices(cls: type, name: str) -> tuple[str, ...]:
    """The values of a ``Literal[...]`` field of a config dataclass (the help's choices come from the type)."""
    return tuple(str(v) for v in typing.get_args(field_types(cls)[name]))


def _choice_enum(name: str, values: tuple[str, ...]) -> type[enum.StrEnum]:
    return enum.StrEnum(name, {v: v for v in values})  # type: ignore[return-value]


Detector = _choice_enum("Detector", literal_choices(DetectorConfig, "backend"))


def _complete_set(incomplete: str) -> list[str]:
    from pavemap.config import field_names

    return [f"{k}=" for k in field_names() if k.startswith(incomplete)]


CONFIG = typer.Option(
    None, "--config", "-c", metavar="PRESET|FILE.yaml",
    help="Preset (nuscenes, kitti) or a YAML config file. Default: from the rig (one camera: kitti; "
         "a surround rig: nuscenes).",
)
SET = typer.Option(
    None, "--set", "-s", metavar="SECTION.FIELD=VALUE", autocompletion=_complete_set,
    help="Override any config field, e.g. --set filter.tau_road=0.6 mesh.epochs=3 (repeatable; several "
         "pairs may follow one --set). `pavemap config` lists every field.",
)
DEVICE = typer.Option(None, "--device", help=f"{DEVICE_HELP} (= --set device=...). Default: the config's, auto.")
EPOCHS = typer.Option(None, "--epochs", help="Mesh training epochs (= --set mesh.epochs=N).")
CRS = typer.Option(None, "--crs", help="CRS of the GeoTIFF and GIS layers of a georeferenced run: auto (the "
                   "drive's UTM zone) or e.g. EPSG:25832 (= --set output.crs=...).")
DETECTOR = typer.Option(
    None, "--detector", case_sensitive=False,
    help="auto: sim where the sequence has synthetic truth, else yolo with the shipped weights "
         "(= --set detector.backend=...). Default: the config's, auto.",
)
WEIGHTS = typer.Option(None, "--weights", help="YOLO detection weights .pt (= --set detector.weights=...; "
                       "implies --detector yolo).")
DETECTIONS = typer.Option(None, "--detections", help="A detections JSONL or a folder of YOLO txt files "
                          "(= --set detector.file=...; implies --detector file).")


def _text(value: object) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, enum.Enum):
        return str(value.value)
    if isinstance(value, list | tuple):
        return ",".join(_text(v) for v in value)
    return str(value)


def shortcut_overrides(shortcuts: Mapping[str, object]) -> list[str]:
    """``{"mesh.epochs": 3, "device": None}`` → ``["mesh.epochs=3"]`` (None: the flag was not given)."""
    return [f"{key}={_text(value)}" for key, value in shortcuts.items() if value is not None]


def detector_shortcuts(detector: enum.Enum | None, weights: Path | None, detections: Path | None) -> dict:
    """``--detector``, ``--weights`` and ``--detections`` as overrides; weights imply yolo, a file implies file."""
    backend = detector.value if detector is not None else None
    if backend is None and weights is not None:
        backend = "yolo"
    if backend is None and detections is not None:
        backend = "file"
    return {"detector.backend": backend, "detector.weights": weights, "detector.file": detections}


def resolve_config(seq: Sequence | None, config: str | None, sets: list[str] | None,
                   shortcuts: Mapping[str, object] | None = None) -> RunConfig:
    """``--config`` (or the rig's preset), then the shortcut flags, then ``--set``; validated.

    Prints which preset is used and why, so a front-camera drive never silently gets the surround preset.
    """
    from pavemap.config import load_config, mount_height_prior, preset_for

    rig, why = preset_for(seq) if seq is not None else ("nuscenes", "no sequence, so the nuscenes preset")
    overrides = [*shortcut_overrides(shortcuts or {}), *(sets or [])]
    cfg = load_config(config, default_preset=rig, overrides=overrides)
    said = mount_height_prior(cfg, seq, config, overrides)
    if said:
        typer.echo(said, err=True)
    if config is None:
        note = f"preset {cfg.preset} ({why}; --config to choose)"
    elif config == cfg.preset:
        note = f"preset {cfg.preset}"
    else:
        note = f"{config} on the {cfg.preset} preset"
    typer.echo(f"config: {note}", err=True)  # stderr: `pavemap config > my.yaml` stays pure YAML
    return cfg


def announce_detector(cfg: RunConfig, seq: Sequence, threshold: bool = False) -> DetectorConfig:
    """Say which detector runs and why (``auto`` resolved), and with ``threshold`` the confidence threshold the
    run will use (the detector's operating point unless the config gives one); a missing input fails here,
    before any stage.

    Returns the detector section with the concrete backend (and the yolo weights' path).
    """
    from pavemap.detect.backends import detector_model, resolve_backend, resolved_filter

    det, why = resolve_backend(cfg.detector, seq)
    typer.echo(f"detector: {det.backend} ({why})", err=True)
    if threshold:
        typer.echo(resolved_filter(cfg.filter, cfg.preset, detector_model(det, seq))[1], err=True)
    return det
