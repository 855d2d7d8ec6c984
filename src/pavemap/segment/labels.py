"""Semantic label maps: presets (RoMe's label sets, Mapillary Vistas), YAML class maps, label-PNG folders.

A :class:`LabelMap` is the sequence's label table (``classes``, with road / movable / sky
flags) plus how to get there from a source labelling: ``lut`` maps source label ids in the
PNGs (0..255) to the table's ids, ``names`` maps a segmentation model's class names.

Class-map YAML (``--class-map``)::

    classes:                 # the label table written to sequence.json
      - {id: 0, name: road, road: true}
      - {id: 1, name: lane_marking, road: true}
      - {id: 2, name: vehicle, movable: true}
      - {id: 3, name: other}
    remap: {13: 0, 24: 1, 55: 2}    # optional: source PNG id -> table id
    names: {"construction--flat--road": road}   # optional: model class name -> table class name
    default: other           # optional: id or name for source ids not in remap
    # or start from a preset and override:  preset: mapillary-vistas

Without ``remap`` the PNG values are the table's ids (identity).
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pavemap.errors import PavemapError
from pavemap.palette import PAVEMAP_CLASSES
from pavemap.types import SemanticClass


@dataclass
class LabelMap:
    name: str
    classes: list[SemanticClass]
    lut: np.ndarray  # (256,) uint8: source label id -> table id
    names: dict[str, int] = field(default_factory=dict)  # normalised model class name -> table id

    def remap(self, labels: np.ndarray) -> np.ndarray:
        """(H, W) source ids (any int dtype, values 0..255) → (H, W) uint8 table ids."""
        return self.lut[labels]

    def id_of(self, name: str) -> int:
        for c in self.classes:
            if c.name == name:
                return c.id
        raise KeyError(name)


def _norm(s: str) -> str:
    return re.sub(r"[\s_\-]+", "", str(s)).lower()


# RoMe's road label sets: road surface classes (road=True) are what the mesh learns and
# the filter keeps; movable objects are masked out of the losses; "other" takes the rest.
_ROME_NUSCENES = [
    SemanticClass(0, "road", road=True),
    SemanticClass(1, "lane_marking", road=True),
    SemanticClass(2, "crosswalk", road=True),
    SemanticClass(3, "manhole", road=True),
    SemanticClass(4, "curb"),
    SemanticClass(5, "sidewalk"),
    SemanticClass(6, "movable", movable=True),
    SemanticClass(7, "other"),
    SemanticClass(8, "sky", sky=True),
]
_ROME_KITTI = [
    SemanticClass(0, "road", road=True),
    SemanticClass(1, "lane_marking", road=True),
    SemanticClass(2, "curb"),
    SemanticClass(3, "sidewalk"),
    SemanticClass(4, "movable", movable=True),
    SemanticClass(5, "other"),
    SemanticClass(6, "sky", sky=True),
]
#: Cityscapes' 19 train ids (what ESPNet / ESPNetv2 output), their background (19) and the ego vehicle
#: (20: the camera's ego mask, painted over the model's output; movable, so no stage uses it as ground).
CITYSCAPES_NAMES = ["road", "sidewalk", "building", "wall", "fence", "pole", "traffic_light", "traffic_sign",
                    "vegetation", "terrain", "sky", "person", "rider", "car", "truck", "bus", "train", "motorcycle",
                    "bicycle"]
_CITYSCAPES = [
    SemanticClass(i, n, road=n == "road", movable=i >= 11, sky=n == "sky") for i, n in enumerate(CITYSCAPES_NAMES)
] + [SemanticClass(19, "other"), SemanticClass(20, "ego", movable=True),
      # labelled road by the network but off the road plane (pavemap.segment.plane_check): not ground
      SemanticClass(21, "above_road", movable=True)]
#: pavemap's own table (the synthetic world's ids; importers default to it).
_PAVEMAP = PAVEMAP_CLASSES

#: Mapillary Vistas v1.2 label ids (config_v1.2.json order) → RoMe nuScenes-style class names.
VISTAS_V12 = [
    "animal--bird", "animal--ground-animal", "construction--barrier--curb", "construction--barrier--fence",
    "construction--barrier--guard-rail", "construction--barrier--other-barrier", "construction--barrier--wall",
    "construction--flat--bike-lane", "construction--flat--crosswalk-plain", "construction--flat--curb-cut",
    "construction--flat--parking", "construction--flat--pedestrian-area", "construction--flat--rail-track",
    "construction--flat--road", "construction--flat--service-lane", "construction--flat--sidewalk",
    "construction--structure--bridge", "construction--structure--building", "construction--structure--tunnel",
    "human--person", "human--rider--bicyclist", "human--rider--motorcyclist", "human--rider--other-rider",
    "marking--crosswalk-zebra", "marking--general", "nature--mountain", "nature--sand", "nature--sky",
    "nature--snow", "nature--terrain", "nature--vegetation", "nature--water", "object--banner", "object--bench",
    "object--bike-rack", "object--billboard", "object--catch-basin", "object--cctv-camera",
    "object--fire-hydrant", "object--junction-box", "object--mailbox", "object--manhole", "object--phone-booth",
    "object--pothole", "object--street-light", "object--support--pole", "object--support--traffic-sign-frame",
    "object--support--utility-pole", "object--traffic-light", "object--traffic-sign--back",
    "object--traffic-sign--front", "object--trash-can", "object--vehicle--bicycle", "object--vehicle--boat",
    "object--vehicle--bus", "object--vehicle--car", "object--vehicle--caravan", "object--vehicle--motorcycle",
    "object--vehicle--on-rails", "object--vehicle--other-vehicle", "object--vehicle--trailer",
    "object--vehicle--truck", "object--vehicle--wheeled-slow", "void--car-mount", "void--ego-vehicle",
    "void--unlabeled",
]


def _vistas_target(name: str) -> str:
    if name in ("construction--flat--road", "construction--flat--bike-lane", "construction--flat--service-lane",
                "construction--flat--parking", "object--pothole", "object--catch-basin"):
        return "road"
    if name in ("marking--general",):
        return "lane_marking"
    if name in ("marking--crosswalk-zebra", "construction--flat--crosswalk-plain"):
        return "crosswalk"
    if name == "object--manhole":
        return "manhole"
    if name in ("construction--barrier--curb", "construction--flat--curb-cut"):
        return "curb"
    if name in ("construction--flat--sidewalk", "construction--flat--pedestrian-area"):
        return "sidewalk"
    if name.startswith(("human--", "object--vehicle--", "animal--")) or name in (
        "void--car-mount", "void--ego-vehicle",
    ):
        return "movable"  # also masks the ego vehicle's bonnet and mount
    if name == "nature--sky":
        return "sky"
    return "other"


def _identity(name: str, classes: list[SemanticClass], default: str = "other") -> LabelMap:
    lut = np.full(256, next(c.id for c in classes if c.name == default), dtype=np.uint8)
    for c in classes:
        lut[c.id] = c.id
    return LabelMap(name, list(classes), lut, {_norm(c.name): c.id for c in classes})


def _vistas() -> LabelMap:
    classes = list(_ROME_NUSCENES)
    ids = {c.name: c.id for c in classes}
    lut = np.full(256, ids["other"], dtype=np.uint8)
    names = {_norm(c.name): c.id for c in classes}
    for i, n in enumerate(VISTAS_V12):
        lut[i] = ids[_vistas_target(n)]
        names[_norm(n)] = ids[_vistas_target(n)]
    return LabelMap("mapillary-vistas", classes, lut, names)


def _pavemap() -> LabelMap:
    lm = _identity("pavemap", _PAVEMAP, default="terrain")
    return lm


PRESETS = {
    "rome-nuscenes": lambda: _identity("rome-nuscenes", _ROME_NUSCENES),
    "rome-kitti": lambda: _identity("rome-kitti", _ROME_KITTI),
    "mapillary-vistas": _vistas,
    "pavemap": _pavemap,
    "cityscapes": lambda: _identity("cityscapes", _CITYSCAPES),
}


def _classes_from_yaml(items: object, file: Path) -> list[SemanticClass]:
    if not isinstance(items, list) or not items:
        raise PavemapError(f"{file}: 'classes' must be a non-empty list of {{id, name, road, movable, sky}}")
    out = []
    for i, c in enumerate(items):
        try:
            cid = int(c["id"])
            sc = SemanticClass(cid, str(c["name"]), bool(c.get("road", False)), bool(c.get("movable", False)),
                               bool(c.get("sky", False)))
        except (KeyError, TypeError, ValueError) as e:
            raise PavemapError(f"{file}: classes[{i}] needs id and name ({e})") from None
        if not 0 <= cid <= 255:
            raise PavemapError(f"{file}: classes[{i}] id {cid} outside 0..255")
        out.append(sc)
    if len({c.id for c in out}) != len(out):
        raise PavemapError(f"{file}: class ids repeat")
    if not any(c.road for c in out):
        raise PavemapError(f"{file}: no class is marked road: true (the filter needs the road classes)")
    return out


def load_label_map(spec: str | os.PathLike) -> LabelMap:
    """A preset name (``rome-nuscenes``, ``rome-kitti``, ``mapillary-vistas``, ``pavemap``, ``cityscapes``) or a
    YAML file."""
    s = str(spec)
    if s in PRESETS:
        return PRESETS[s]()
    path = Path(s)
    if not path.is_file():
        raise PavemapError(f"class map {s!r}: no such file and not a preset; presets: {', '.join(PRESETS)}")

    from pavemap.io.yamlfile import read_yaml

    d = read_yaml(path, "class map")
    if not isinstance(d, dict):
        raise PavemapError(f"{path}: expected a mapping with 'classes' (and optional remap, names, default)")
    if "preset" in d:
        if d["preset"] not in PRESETS:
            raise PavemapError(f"{path}: unknown preset {d['preset']!r}; presets: {', '.join(PRESETS)}")
        base = PRESETS[d["preset"]]()
    else:
        base = None
    classes = _classes_from_yaml(d["classes"], path) if "classes" in d else (base.classes if base else None)
    if classes is None:
        raise PavemapError(f"{path}: needs 'classes' or 'preset'")
    by_name = {c.name: c.id for c in classes}
    ids = set(by_name.values())

    def target(v: object, where: str) -> int:
        if isinstance(v, int) and not isinstance(v, bool) and v in ids:
            return v
        if isinstance(v, str) and v in by_name:
            return by_name[v]
        raise PavemapError(f"{path}: {where}: {v!r} is not a class id or name of {sorted(by_name)}")

    if "default" in d:
        default = target(d["default"], "default")
    elif "other" in by_name:
        default = by_name["other"]
    else:
        default = None
    if "remap" in d:
        if not isinstance(d["remap"], dict):
            raise PavemapError(f"{path}: 'remap' must map source label ids to class ids or names")
        lut = np.full(256, 255 if default is None else default, dtype=np.uint8)
        for k, v in d["remap"].items():
            try:
                src = int(k)
            except (TypeError, ValueError):
                raise PavemapError(f"{path}: remap key {k!r} is not a label id 0..255") from None
            if not 0 <= src <= 255:
                raise PavemapError(f"{path}: remap key {src} outside 0..255")
            lut[src] = target(v, f"remap[{k}]")
        if default is None and (lut == 255).any() and 255 not in ids:
            raise PavemapError(f"{path}: source ids outside 'remap' need a 'default' class")
    elif base is not None and "classes" not in d:
        lut = base.lut.copy()
    else:
        lut = np.full(256, 0 if default is None else default, dtype=np.uint8)
        lut[list(ids)] = list(ids)
        if default is None:
            lut[[i for i in range(256) if i not in ids]] = 255  # marks "unknown" for the check in remap_labels
    names = dict(base.names) if base is not None and "classes" not in d else {}
    names.update({_norm(c.name): c.id for c in classes})
    for k, v in (d.get("names") or {}).items():
        names[_norm(k)] = target(v, f"names[{k!r}]")
    return LabelMap(path.stem, classes, lut, names)


def find_label_file(labels_dir: Path, camera: str, frame: int, image_rel: str, n_cameras: int) -> Path | None:
    """The label PNG of a view: ``<dir>/<camera>/<frame:06d>.png``, ``<dir>/<camera>/<image stem>.png``,
    or (one camera) ``<dir>/<frame:06d>.png`` / ``<dir>/<image stem>.png``."""
    stem = Path(image_rel).stem
    cands = [labels_dir / camera / f"{frame:06d}.png", labels_dir / camera / f"{stem}.png"]
    if n_cameras == 1:
        cands += [labels_dir / f"{frame:06d}.png", labels_dir / f"{stem}.png"]
    for c in cands:
        if c.is_file():
            return c
    return None
