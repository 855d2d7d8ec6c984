"""Map a detector's own class names to pavemap's defect classes (D00, D10, D20, D40).

A YOLO model trained on RDD2022 or a user's data names its classes its own way
(``D00``, ``d40``, ``Pothole``, ``longitudinal crack``, ``D43``, ``Repair``...). pavemap
keeps four classes (SPEC §0). The mapping is by name:

- a name equal (case and separators ignored) to a code ``D00/D10/D20/D40`` or to one
  of the aliases below maps to that class;
- every other name is dropped (RDD2022's D43 crosswalk blur, D44 white line blur,
  D50 manhole, Repair, ...), and reported once;
- an override map (YAML) wins over both. Its keys are model class names or indices,
  its values a code, a pavemap class id 0..3, or ``drop``::

      # class_map.yaml
      D43: drop
      Repair: drop
      pothole_deep: D40
      7: D20

  The mapping may also sit under a top-level ``map:`` key.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np

from pavemap.errors import PavemapError
from pavemap.types import DEFECT_CODES

DROP = -1

ALIASES: dict[str, str] = {
    "longitudinalcrack": "D00",
    "longitudinal": "D00",
    "lateralcrack": "D10",
    "transversecrack": "D10",
    "transverse": "D10",
    "alligatorcrack": "D20",
    "alligator": "D20",
    "crocodilecrack": "D20",
    "pothole": "D40",
    "potholes": "D40",
}


def _norm(name: str) -> str:
    return re.sub(r"[\s_\-]+", "", str(name)).lower()


def _code_of(value: object, where: str) -> int:
    """A map value → pavemap class id or DROP."""
    if isinstance(value, bool):
        raise PavemapError(f"{where}: {value!r} is not a class; use D00, D10, D20, D40, 0..3 or drop")
    if isinstance(value, int):
        if 0 <= value < len(DEFECT_CODES):
            return value
        raise PavemapError(f"{where}: class id {value} outside 0..3 (0 D00, 1 D10, 2 D20, 3 D40)")
    if value is None:
        return DROP
    s = _norm(str(value))
    if s in ("drop", "ignore", "none", "skip"):
        return DROP
    for i, code in enumerate(DEFECT_CODES):
        if s == code.lower():
            return i
    if s in ALIASES:
        return DEFECT_CODES.index(ALIASES[s])
    raise PavemapError(f"{where}: unknown target {value!r}; use one of {', '.join(DEFECT_CODES)} or drop")


def default_class(name: str) -> int:
    """pavemap class id for a model class name, DROP when it is not one of the four."""
    s = _norm(name)
    for i, code in enumerate(DEFECT_CODES):
        if s == code.lower():
            return i
    if s in ALIASES:
        return DEFECT_CODES.index(ALIASES[s])
    return DROP


def load_class_map(path: str | os.PathLike) -> dict[str, int]:
    """Read an override YAML → {normalised model class name or index string: class id or DROP}."""

    path = Path(path)
    from pavemap.io.yamlfile import read_yaml

    data = read_yaml(path, "class map")
    if isinstance(data, dict) and isinstance(data.get("map"), dict):
        data = data["map"]
    if not isinstance(data, dict) or not data:
        raise PavemapError(f"{path}: a class map must be a mapping of model class -> D00/D10/D20/D40/drop")
    return {_norm(str(k)): _code_of(v, f"{path}: entry {k!r}") for k, v in data.items()}


def build_class_map(
    names: dict[int, str] | list[str], overrides: dict[str, int] | None = None
) -> tuple[np.ndarray, list[str]]:
    """Lookup table model class index → pavemap class id (DROP = -1), and the dropped names.

    ``names`` is the model's ``{index: name}`` (ultralytics ``model.names``). Returns
    ``lut`` (n_model_classes,) int64 and the sorted list of model class names that are dropped.
    """
    if isinstance(names, (list, tuple)):
        names = dict(enumerate(names))
    n = max(names) + 1 if names else 0
    lut = np.full(n, DROP, dtype=np.int64)
    overrides = overrides or {}
    for i, name in names.items():
        key_name, key_idx = _norm(name), str(i)
        if key_name in overrides:
            lut[i] = overrides[key_name]
        elif key_idx in overrides:
            lut[i] = overrides[key_idx]
        else:
            lut[i] = default_class(name)
    dropped = sorted(str(names[i]) for i in names if lut[i] == DROP)
    if not np.any(lut >= 0):
        raise PavemapError(
            f"no model class maps to a defect class: model classes are {[names[i] for i in sorted(names)]}; "
            "give a class map (--class-map YAML: 'model name: D00|D10|D20|D40|drop')"
        )
    return lut, dropped
