"""The batch manifest: which drives make up a road network survey, when they were driven, by what.

A YAML file::

    config: kitti                 # optional: a preset or a YAML config (relative to the manifest);
                                  # without it each drive gets the preset that fits its rig
    set: [mesh.epochs=4]          # optional: config overrides for every drive
    drives:
      - path: seqs/jan_van1       # a sequence folder (relative to the manifest)
        date: 2026-01-05          # survey date, ISO 8601
        name: jan-van1            # optional: the drive's folder under NETWORK/drives (default: the folder name)
        vehicle: van 1            # optional free text
        camera: front 1241x376    # optional free text
        set: [detector.seed=1]    # optional: overrides for this drive only

Every problem is a PavemapError naming the manifest file and the entry (``drives[2] (jan-van1)``).
"""

from __future__ import annotations

import datetime as dt
import os
import re
from dataclasses import dataclass, field
from pathlib import Path

from pavemap.errors import PavemapError

#: A drive name becomes a folder name and a GeoPackage value: keep it portable.
NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,63}$")
DRIVE_KEYS = ("path", "date", "name", "vehicle", "camera", "set")
TOP_KEYS = ("drives", "config", "set")


@dataclass(frozen=True)
class Drive:
    """One drive of the manifest, its path resolved."""

    name: str
    path: Path  # the sequence folder (absolute)
    date: dt.date
    vehicle: str = ""
    camera: str = ""
    overrides: tuple[str, ...] = ()


@dataclass(frozen=True)
class Manifest:
    path: Path
    drives: tuple[Drive, ...]
    config: str | None = None  # a preset name or an absolute YAML path
    overrides: tuple[str, ...] = field(default_factory=tuple)


def _overrides(value: object, where: str) -> tuple[str, ...]:
    if value is None:
        return ()
    if isinstance(value, str):
        value = [value]
    if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
        raise PavemapError(f"{where}: 'set' must be a list of section.field=value texts, e.g. [mesh.epochs=4]")
    return tuple(value)


def _date(value: object, where: str) -> dt.date:
    if isinstance(value, dt.datetime):
        return value.date()
    if isinstance(value, dt.date):
        return value
    if isinstance(value, str):
        try:
            return dt.date.fromisoformat(value.strip())
        except ValueError:
            pass
    raise PavemapError(f"{where}: date {value!r} is not an ISO date (YYYY-MM-DD, e.g. 2026-01-05)")


def _text(value: object, key: str, where: str) -> str:
    if value is None:
        return ""
    if not isinstance(value, str | int | float):
        raise PavemapError(f"{where}: {key} must be text, got {type(value).__name__}")
    return str(value)


def _drive(entry: object, i: int, base: Path, where_file: str) -> Drive:
    where = f"{where_file}: drives[{i}]"
    if not isinstance(entry, dict):
        raise PavemapError(f"{where}: each drive must be a mapping with path and date, got {type(entry).__name__}")
    if isinstance(entry.get("name"), str):
        where += f" ({entry['name']})"
    unknown = sorted(str(k) for k in entry if k not in DRIVE_KEYS)
    if unknown:
        raise PavemapError(f"{where}: unknown key(s) {unknown}; a drive has {', '.join(DRIVE_KEYS)}")
    for key in ("path", "date"):
        if entry.get(key) in (None, ""):
            raise PavemapError(f"{where}: '{key}' is missing")
    if not isinstance(entry["path"], str):
        raise PavemapError(f"{where}: path must be text (a sequence folder), got {entry['path']!r}")
    path = Path(os.path.expanduser(entry["path"]))
    path = (path if path.is_absolute() else base / path).resolve()
    if not (path / "sequence.json").is_file():
        what = "does not exist" if not path.exists() else "holds no sequence.json (is it a sequence folder?)"
        raise PavemapError(f"{where}: path {entry['path']!r} ({path}) {what}")
    name = _text(entry.get("name"), "name", where) or path.name
    if not NAME_RE.match(name):
        raise PavemapError(f"{where}: name {name!r} must be 1-64 letters, digits, '.', '_' or '-' (it names a folder)")
    return Drive(name, path, _date(entry["date"], where), _text(entry.get("vehicle"), "vehicle", where),
                 _text(entry.get("camera"), "camera", where), _overrides(entry.get("set"), where))


def load_manifest(path: str | os.PathLike) -> Manifest:
    """Read and check a manifest; paths are resolved against the manifest's folder."""
    from pavemap.io.yamlfile import read_yaml

    p = Path(path)
    data = read_yaml(p, "manifest")
    if not isinstance(data, dict) or not isinstance(data.get("drives"), list) or not data["drives"]:
        raise PavemapError(f"{p}: a manifest needs 'drives:', a list of drives (each with path and date)")
    unknown = sorted(str(k) for k in data if k not in TOP_KEYS)
    if unknown:
        raise PavemapError(f"{p}: unknown key(s) {unknown}; a manifest has {', '.join(TOP_KEYS)}")
    base = p.resolve().parent
    drives = tuple(_drive(e, i, base, str(p)) for i, e in enumerate(data["drives"]))
    seen: dict[str, int] = {}
    for i, d in enumerate(drives):
        if d.name in seen:
            raise PavemapError(f"{p}: drives[{i}] ({d.name}): the name is used by drives[{seen[d.name]}] too; "
                               "give each drive its own name")
        seen[d.name] = i
    config = data.get("config")
    if config is not None:
        if not isinstance(config, str):
            raise PavemapError(f"{p}: config must be a preset name or a YAML file, got {config!r}")
        from pavemap.config import PRESETS

        if config not in PRESETS:
            cp = Path(os.path.expanduser(config))
            cp = cp if cp.is_absolute() else base / cp
            if not cp.is_file():
                raise PavemapError(f"{p}: config {config!r} is neither a preset ({', '.join(PRESETS)}) nor a file")
            config = str(cp.resolve())
    return Manifest(p.resolve(), drives, config, _overrides(data.get("set"), f"{p}: set"))


__all__ = ["Drive", "Manifest", "load_manifest"]
