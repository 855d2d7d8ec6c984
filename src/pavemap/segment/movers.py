"""Where things that move are, for SfM: features on a passing bus or a parked car that drives off pull the
camera's path with them, so SfM and the car's planar motion match only the static scene.

:func:`movable_masks` gives a function image path -> (H, W) bool (True on a person, rider, car, truck, bus,
train, motorcycle or bicycle, grown by a margin), from the ESPNet segmenter when its weights are found and the
images are in colour; otherwise None, and the caller says that SfM runs unmasked.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable
from pathlib import Path

import numpy as np

from pavemap.errors import PavemapError

log = logging.getLogger(__name__)

MoverMasks = Callable[[Path], "np.ndarray | None"]


def movable_masks(spec: str | None = "auto", weights: str | os.PathLike | None = None, device: str = "cpu",
                  grow: float = 0.01) -> tuple[MoverMasks | None, str]:
    """(mask function or None, what was done, one line).

    ``spec``: the ``--segmenter`` value (``auto``: ESPNetv2 when its weights are found; ``espnet`` / ``espnetv2``
    required; anything else, e.g. ``none``, ``corridor`` or a .pt file: no masks). ``grow``: the masks are
    dilated by this share of the image width (a vehicle's outline and its shadow's edge). The function's
    ``segmenter`` remembers what it labelled (:meth:`~pavemap.segment.espnet.EspnetSegmenter.remember`): the
    import's semantics take it, and the keyframes SfM masked are not labelled twice.
    """
    from pavemap.segment.espnet import ARCHS, DEFAULT, EspnetSegmenter, find_weights

    arch = DEFAULT if spec in (None, "auto") else spec
    if arch not in ARCHS:
        return None, f"SfM: no vehicle masks (--segmenter {spec})"
    try:
        find_weights(arch, weights)
    except PavemapError as e:
        if spec not in (None, "auto"):
            raise
        return None, f"SfM: no vehicle masks ({e})"
    seg = EspnetSegmenter(arch, weights, device=device).remember()
    return _Masker(seg, grow), f"SfM: vehicles and people masked by the {seg.arch.name} segmenter ({seg.path.name})"


class _Masker:
    """image path -> (H, W) bool movable mask (None on a grey image). ``segmenter`` remembers what it labelled:
    the import's semantics reuse it (:func:`pavemap.segment.auto.espnet_semantics`)."""

    def __init__(self, segmenter: object, grow: float):
        self.segmenter, self.grow = segmenter, grow
        self.movable = np.array([c.movable and c.name != "ego" for c in segmenter.classes], dtype=bool)  # type: ignore[attr-defined]

    def __call__(self, path: Path) -> np.ndarray | None:
        import cv2

        from pavemap.io.sequence import load_rgb
        from pavemap.segment.espnet import is_grey

        rgb = load_rgb(path)
        if is_grey(rgb):
            return None
        lab = self.segmenter.segment([rgb])[0]  # type: ignore[attr-defined]
        m = self.movable[np.minimum(lab, len(self.movable) - 1)]
        k = max(1, int(round(self.grow * m.shape[1])))
        return cv2.dilate(m.astype(np.uint8), np.ones((2 * k + 1, 2 * k + 1), np.uint8)) > 0


__all__ = ["MoverMasks", "movable_masks"]
