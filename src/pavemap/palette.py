"""Colours shared by every picture pavemap draws, and pavemap's own semantic class table.

The one home of the map colours the HTML report, the network page and the QGIS layer styles
(:mod:`pavemap.export.qgis_style`) share: defect classes, urgency, register status, condition index bands.
"""

from __future__ import annotations

import hashlib

import numpy as np

from pavemap.types import SemanticClass

#: pavemap's own label table: the synthetic world's ids; importers default to it.
PAVEMAP_CLASSES: list[SemanticClass] = [
    SemanticClass(0, "road", road=True),
    SemanticClass(1, "lane_marking", road=True),
    SemanticClass(2, "curb"),
    SemanticClass(3, "sidewalk"),
    SemanticClass(4, "terrain"),
    SemanticClass(5, "vehicle", movable=True),
    SemanticClass(6, "building"),
    SemanticClass(7, "sky", sky=True),
]

#: Defect classes D00 green, D10 yellow, D20 orange, D40 red (the paper's Figure 11 colours).
DEFECT_HEX: dict[str, str] = {"D00": "#2ca02c", "D10": "#f5d300", "D20": "#ff7f0e", "D40": "#d62728"}
DEFECT_RGB: dict[int, tuple[int, int, int]] = {
    i: tuple(int(h[k : k + 2], 16) for k in (1, 3, 5)) for i, h in enumerate(DEFECT_HEX.values())
}

#: Urgency (the ``priority`` field, :data:`pavemap.maintain.policy.PRIORITIES`) as the report's map draws it;
#: "inspect" / "no action" are the labels of runs before issue 16.
PRIORITY_HEX: dict[str, str] = {"repair now": "#c0392b", "schedule": "#e67e22", "inspect": "#e67e22",
                                "monitor": "#f1c40f", "no action": "#95a5a6", "unassessed": "#95a5a6"}
#: A register defect's status (network page and register.gpkg).
STATUS_HEX: dict[str, str] = {"new": "#d62728", "grown": "#ff7f0e", "unchanged": "#1f77b4",
                              "not seen again": "#9467bd"}
#: PCI-like condition index 0-100 in the usual PCI rating bands: (upper bound, colour), red failed .. green good.
CONDITION_BANDS: tuple[tuple[float, str], ...] = ((25, "#8e1b10"), (40, "#c0392b"), (55, "#e67e22"),
                                                  (70, "#f1c40f"), (85, "#9ccc65"), (float("inf"), "#2e7d32"))
#: A segment without an index ("not assessed": not seen well enough), never green.
NOT_ASSESSED_HEX = "#9e9e9e"
#: The drive's trajectory line in the GIS styles (the report's accent blue).
TRAJECTORY_HEX = "#1565c0"


def index_colour(v: float) -> str:
    """PCI-like index 0-100 -> the colour of its band in :data:`CONDITION_BANDS`."""
    return next(col for lim, col in CONDITION_BANDS if v < lim)


# Cityscapes-like colours for common class names; other names get a stable hashed colour.
_NAMED: dict[str, tuple[int, int, int]] = {
    "road": (128, 64, 128), "lane_marking": (255, 255, 255), "lane marking": (255, 255, 255),
    "crosswalk": (230, 230, 230), "manhole": (90, 90, 140), "sidewalk": (244, 35, 232), "curb": (196, 196, 0),
    "terrain": (107, 142, 35), "vegetation": (107, 142, 35), "car": (0, 0, 142), "vehicle": (0, 0, 142),
    "movable": (0, 0, 142), "person": (220, 20, 60), "pedestrian": (220, 20, 60), "building": (70, 70, 70),
    "sky": (70, 130, 180), "other": (80, 80, 80), "ego": (0, 0, 0),
}


def class_colour(c: SemanticClass) -> tuple[int, int, int]:
    """A stable colour per class: by name, purple for unknown road-like classes, else hashed."""
    name = str(c.name).lower()
    if name in _NAMED:
        return _NAMED[name]
    if c.road:
        return (128, 64, 128)
    h = hashlib.md5(name.encode()).digest()
    return (h[0], h[1], h[2])


def semantic_palette(classes: list[SemanticClass]) -> np.ndarray:
    """(257, 3) uint8 lookup table: row = class id, row 256 = no label (black)."""
    pal = np.zeros((257, 3), dtype=np.uint8)
    for c in classes:
        if 0 <= int(c.id) <= 255:
            pal[int(c.id)] = class_colour(c)
    return pal


def colour_labels(labels: np.ndarray, classes: list[SemanticClass]) -> np.ndarray:
    """(..., ) int class ids (-1 or out of range = none) -> (..., 3) uint8 colours, black where none."""
    lab = np.asarray(labels)
    idx = np.where((lab < 0) | (lab > 255), 256, lab).astype(np.int64)
    return semantic_palette(classes)[idx]
