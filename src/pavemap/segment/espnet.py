"""The road / vehicle segmenter: ESPNet or ESPNetv2 trained on Cityscapes, offline, CPU or CUDA.

``EspnetSegmenter("espnet")`` loads the published Cityscapes weights (found by
:func:`find_weights`) into pavemap's own model code (:mod:`~pavemap.segment.espnet_model`,
:mod:`~pavemap.segment.espnetv2_model`) and labels images with the ``cityscapes`` table
(:mod:`pavemap.segment.labels`): road (road), sidewalk, …, person … bicycle (movable), sky,
``other`` (the model's background) and ``ego`` (the ego vehicle from the camera's ego mask:
Cityscapes has no bonnet class and the model calls it road).

Where the weights are looked for, first hit wins: ``--segmenter-weights PATH``;
``$PAVEMAP_WEIGHTS/<file>``; the user's weight folders (:func:`pavemap.user_cache.weight_dirs`, where
``pavemap weights install`` puts a file); a ``shared/data/pretrained/<folder>/<file>`` beside the source
checkout (the project's development machines). See docs/segmenter.md and docs/weights.md.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pavemap.errors import PavemapError
from pavemap.segment.labels import PRESETS
from pavemap.types import SemanticClass

log = logging.getLogger(__name__)

N_CLASSES = 20  # 19 Cityscapes train ids + background


@dataclass(frozen=True)
class Arch:
    """One supported network: its weight file, input size and normalisation."""

    name: str
    folder: str
    file: str
    build: Callable
    mean: tuple[float, float, float]  # per channel, in the channel order below, on the scale of ``scale``
    std: tuple[float, float, float]
    bgr: bool  # channel order the model was trained on
    pre_scale: bool  # True: /255 before normalising (ImageNet style); False: normalise 0..255, resize, then /255
    multiple: int  # input sides must be multiples of this


def _espnet() -> object:
    from pavemap.segment.espnet_model import EspNet

    return EspNet(N_CLASSES, p=2, q=8)


def _espnetv2() -> object:
    from pavemap.segment.espnetv2_model import EspNetV2

    return EspNetV2(N_CLASSES)


ARCHS: dict[str, Arch] = {
    # sacmehta/ESPNet VisualizeResults.py: BGR, minus mean, / std (0..255 scale), resize, / 255
    "espnet": Arch("espnet", "espnet-cityscapes", "espnet_p_2_q_8.pth", _espnet,
                   (72.3923111, 82.90893555, 73.15840149), (45.3192215, 46.15289307, 44.91483307), True, False, 8),
    # sacmehta/EdgeNets segmentation transforms: RGB / 255, ImageNet mean and std
    "espnetv2": Arch("espnetv2", "espnetv2-cityscapes", "espnetv2_s_2.0_city_1024x512.pth", _espnetv2,
                     (0.485, 0.456, 0.406), (0.229, 0.224, 0.225), False, True, 16),
}
#: Input width when none is given: the image's own, within these bounds (segment.json: upsampling a
#: 400-px frame to 768 cost 0.11 road IoU; 512-640 were best on the synthetic presets, 768 on 1600-px frames
#: keeps the cost at about 0.3 s a frame here)
MIN_WIDTH, MAX_WIDTH = 512, 768
#: The default network, chosen by measurement (bench/segment_bench.py, docs/segmenter.md).
DEFAULT = "espnetv2"


def weight_dirs() -> list[Path]:
    """The folders searched for weight files (:func:`pavemap.user_cache.weight_search_dirs`)."""
    from pavemap.user_cache import weight_search_dirs

    return weight_search_dirs()


def find_weights(arch: str, weights: str | os.PathLike | None = None) -> Path:
    """The weight file of ``arch``: ``weights`` when given, else the first of :func:`weight_dirs` holding
    ``<file>`` or ``<folder>/<file>``. Missing: a one-line error saying which file to put where."""
    a = ARCHS[arch]
    if weights is not None:
        p = Path(weights).expanduser()
        if not p.is_file():
            raise PavemapError(f"{p}: segmenter weights not found ({a.name} expects {a.file})")
        return p
    dirs = weight_dirs()
    for d in dirs:
        for p in (d / a.file, d / a.folder / a.file):
            if p.is_file():
                return p
    from pavemap.user_cache import install_dir

    raise PavemapError(
        f"{a.file}: {a.name} segmenter weights not found; put the file in {install_dir()} "
        f"(`pavemap weights install FILE`) or give --segmenter-weights PATH; looked in: "
        + ", ".join(str(d) for d in dirs)
    )


def _state_dict(path: Path) -> dict:
    """The plain state dict in ``path`` (a wrapping {"state_dict": …} and "module." prefixes undone)."""
    import torch

    try:
        sd = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # noqa: BLE001 - a damaged pickle fails in many ways (KeyError, EOFError, ...)
        first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise PavemapError(f"{path}: not a readable PyTorch weight file (corrupt or truncated? {first[:160]})") \
            from None
    if isinstance(sd, dict) and isinstance(sd.get("state_dict"), dict):
        sd = sd["state_dict"]
    if not isinstance(sd, dict) or not sd or not all(isinstance(v, torch.Tensor) for v in sd.values()):
        raise PavemapError(f"{path}: not a state dict of tensors (expected the published Cityscapes weights)")
    return {k.removeprefix("module."): v for k, v in sd.items()}


def _check_keys(path: Path, arch: Arch, model: object, sd: dict) -> None:
    """One-line errors for weights of another architecture or class count."""
    want = {k: tuple(v.shape) for k, v in model.state_dict().items()  # type: ignore[attr-defined]
            if not k.endswith("num_batches_tracked")}  # older checkpoints lack the counters; torch fills them
    have = {k: tuple(v.shape) for k, v in sd.items() if not k.endswith("num_batches_tracked")}
    missing, extra = sorted(set(want) - set(have)), sorted(set(have) - set(want))
    if missing or extra:
        other = next((o.name for o in ARCHS.values() if o is not arch and _keys_of(o) == set(have)), None)
        hint = f"; they look like {other} weights (--segmenter {other})" if other else ""
        raise PavemapError(f"{path}: not {arch.name} weights ({len(missing)} missing keys e.g. "
                           f"{(missing or ['-'])[0]!r}, {len(extra)} unexpected e.g. {(extra or ['-'])[0]!r}){hint}")
    bad = [k for k in want if want[k] != have[k]]
    if bad:
        k = bad[0]
        if want[k][:1] == (N_CLASSES,) and have[k][:1] != want[k][:1]:
            raise PavemapError(f"{path}: the weights have {have[k][0]} output classes at {k!r}; the segmenter "
                               f"needs {N_CLASSES} (19 Cityscapes train ids + background)")
        raise PavemapError(f"{path}: {k!r} has shape {have[k]}, {arch.name} needs {want[k]} (another variant?)")


_KEYS: dict[str, set[str]] = {}


def _keys_of(arch: Arch) -> set[str]:
    if arch.name not in _KEYS:
        _KEYS[arch.name] = {k for k in arch.build().state_dict()  # type: ignore[attr-defined]
                            if not k.endswith("num_batches_tracked")}
    return _KEYS[arch.name]


def is_grey(image: np.ndarray, tol: int = 2) -> bool:
    """(H, W, 3) uint8 (or (H, W)): True when the three channels are (nearly) equal everywhere sampled."""
    if image.ndim == 2 or image.shape[2] == 1:
        return True
    s = image[:: max(1, image.shape[0] // 64), :: max(1, image.shape[1] // 64)].astype(np.int16)
    return bool(np.abs(s[..., 0] - s[..., 1]).max() <= tol and np.abs(s[..., 1] - s[..., 2]).max() <= tol)


class EspnetSegmenter:
    """Segmenter over ESPNet / ESPNetv2 Cityscapes weights. See :class:`pavemap.segment.Segmenter`.

    ``width``: network input width (None: the image's width within ``MIN_WIDTH``..``MAX_WIDTH``);
    height = width / 2 (the 2:1 frames it was trained on; images are stretched to it) or, ``keep_aspect``,
    the image's own aspect; labels are resized back (nearest).
    ``device``: as :func:`resolve_device`.
    """

    def __init__(self, arch: str = DEFAULT, weights: str | os.PathLike | None = None, device: str = "auto",
                 width: int | None = None, keep_aspect: bool = True):
        import torch

        from pavemap.device import resolve_device

        if arch not in ARCHS:
            raise PavemapError(f"unknown segmenter {arch!r}; choose {', '.join(ARCHS)} (or an ultralytics .pt file)")
        self.arch = ARCHS[arch]
        self.path = find_weights(arch, weights)
        self.device = resolve_device(device)
        model = self.arch.build()
        sd = _state_dict(self.path)
        _check_keys(self.path, self.arch, model, sd)
        model.load_state_dict(sd, strict=True)
        self.model = model.eval().to(self.device)
        self.width, self.keep_aspect = width, keep_aspect
        lm = PRESETS["cityscapes"]()
        self.classes: list[SemanticClass] = list(lm.classes)
        self.ego_id = lm.id_of("ego")
        self.dtype = torch.float32
        # image digest -> (shape, zlib'd network-size labels): what an import labels for SfM's vehicle masks is
        # not labelled again for the sequence's semantics (:meth:`remember`)
        self.memo: dict[bytes, tuple[tuple[int, int], bytes]] | None = None
        log.info("segmenter %s (%s) on %s, input width %s", self.arch.name, self.path, self.device,
                 width or f"the image's, {MIN_WIDTH}-{MAX_WIDTH}")

    def input_size(self, height: int, width: int) -> tuple[int, int]:
        """(h, w) network input for an image of ``height`` x ``width``: multiples of the network's stride."""
        m = self.arch.multiple
        w = self.width or min(MAX_WIDTH, max(MIN_WIDTH, width))  # never upsample past the image's own detail
        h = w * height / width if self.keep_aspect else w / 2
        return max(m, round(h / m) * m), max(m, round(w / m) * m)

    def _prepare(self, images: list[np.ndarray]) -> object:
        """RGB uint8 images → (B, 3, h, w) float network input on the device, normalised as the model was trained."""
        import torch
        import torch.nn.functional as F  # noqa: N812

        a, out = self.arch, []
        mean = torch.tensor(a.mean, device=self.device).view(1, 3, 1, 1)
        std = torch.tensor(a.std, device=self.device).view(1, 3, 1, 1)
        size = self.input_size(*images[0].shape[:2])
        for im in images:  # images may differ in size (several cameras): resize one by one, then batch
            x = torch.from_numpy(np.ascontiguousarray(im)).to(self.device).permute(2, 0, 1)[None].float()
            if a.bgr:
                x = x.flip(1)
            if a.pre_scale:
                x = (F.interpolate(x / 255.0, size, mode="bilinear", align_corners=False) - mean) / std
            else:
                x = F.interpolate((x - mean) / std, size, mode="bilinear", align_corners=False) / 255.0
            out.append(x)
        return torch.cat(out)

    def logits(self, images: list[np.ndarray]) -> object:
        """(B, 20, h, w) float logits at the network size for RGB uint8 images."""
        import torch

        with torch.inference_mode():
            return self.model(self._prepare(images))

    def remember(self) -> EspnetSegmenter:
        """Keep every image's labels (compressed, at the network's size, ~10-30 kB each) so that the same pixels
        are not run through the network twice; returns self."""
        self.memo = {} if self.memo is None else self.memo
        return self

    def _network_labels(self, images: list[np.ndarray]) -> list[np.ndarray]:
        """(h, w) uint8 labels at the network's size per image, from the memo where it has them."""
        import hashlib
        import zlib

        import torch

        keys = [hashlib.blake2b(np.ascontiguousarray(im).data, digest_size=20,
                                person=str(im.shape).encode()[:16]).digest() if self.memo is not None else b""
                for im in images]
        todo = [i for i, k in enumerate(keys) if self.memo is None or k not in self.memo]
        out: dict[int, np.ndarray] = {}
        if todo:
            lab = self.logits([images[i] for i in todo]).argmax(1).to(torch.uint8).cpu().numpy()  # (B, h, w)
            for j, i in enumerate(todo):
                out[i] = lab[j]
                if self.memo is not None:
                    self.memo[keys[i]] = (lab[j].shape, zlib.compress(lab[j].tobytes(), 1))
        for i in set(range(len(images))) - set(todo):
            shape, z = self.memo[keys[i]]  # type: ignore[index]
            out[i] = np.frombuffer(zlib.decompress(z), np.uint8).reshape(shape)
        return [out[i] for i in range(len(images))]

    def segment(self, images: list[np.ndarray], ego: list[np.ndarray | None] | None = None) -> list[np.ndarray]:
        """(H, W, 3) uint8 RGB each → (H, W) uint8 ``cityscapes`` ids each; ``ego`` (H, W) bool masks → ``ego``."""
        import cv2

        lab = self._network_labels(images)
        out = []
        for i, im in enumerate(images):
            full = cv2.resize(lab[i], (im.shape[1], im.shape[0]), interpolation=cv2.INTER_NEAREST)
            e = ego[i] if ego is not None else None
            if e is not None and e.any():
                full[e] = self.ego_id
            out.append(full)
        return out

