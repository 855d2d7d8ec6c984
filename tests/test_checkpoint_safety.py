"""Stage-1 checkpoints load with ``torch.load(weights_only=True)``: a doctored one is refused, its code never runs."""

from __future__ import annotations

import os
import pickle
from pathlib import Path

import numpy as np
import pytest
import torch

from mesh_scene import read_scene
from pavemap.errors import PavemapError
from pavemap.mesh import MeshConfig, reconstruct
from pavemap.mesh.checkpoint import CHECKPOINT, plain, read_checkpoint


class _Evil:
    marker: Path

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


def _cfg(**kw) -> MeshConfig:
    base = dict(resolution=0.1, crop_m=4.0, epochs=1, render_scale=1.0, eval_scale=1.0, pixels_per_step=512,
                holdout_every=3, device="cpu", threads=1, resume=False, view_range_m=0.0)  # as test_mesh_train
    return MeshConfig(**{**base, **kw})


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A 1-epoch reconstruction's run folder (its checkpoint.pt) and the scene."""
    root = tmp_path_factory.mktemp("ck")
    scene = read_scene(root / "scene", frames=6, width=48, height=32)
    reconstruct(scene, root / "out", _cfg(), progress=False)
    return scene, root / "out"


def test_a_saved_checkpoint_loads_weights_only(trained):
    _, out = trained
    state = torch.load(out / CHECKPOINT, weights_only=True)
    assert state["epoch"] == 1 and isinstance(state["config"], dict) and isinstance(state["history"], list)
    assert all(isinstance(v, torch.Tensor) for v in state["model"].values())
    assert read_checkpoint(out / CHECKPOINT)["epoch"] == 1


def test_plain_converts_numpy_and_refuses_objects():
    got = plain({"a": np.float32(1.5), "b": [np.int64(2), Path("x")], "c": np.zeros(2), "d": (1, "s")})
    assert got["a"] == 1.5 and got["b"] == [2, "x"] and isinstance(got["c"], torch.Tensor) and got["d"] == (1, "s")
    with pytest.raises(TypeError, match=r"checkpoint\.h\[0\]: object cannot go into a checkpoint"):
        plain({"h": [object()]})


def test_a_malicious_checkpoint_is_refused_and_does_not_run(trained, tmp_path):
    scene, out = trained
    _Evil.marker = tmp_path / "pwned"
    doctored = tmp_path / "run"
    doctored.mkdir()
    state = torch.load(out / CHECKPOINT, weights_only=True)
    state["history"].append(_Evil())
    torch.save(state, doctored / CHECKPOINT, pickle_module=pickle)
    with pytest.raises(PavemapError, match=r"checkpoint\.pt: this checkpoint holds objects that cannot be loaded "
                                           r"safely.*--overwrite.*delete the checkpoint"):
        read_checkpoint(doctored / CHECKPOINT)
    with pytest.raises(PavemapError, match="cannot be loaded safely"):  # what a resuming run meets
        reconstruct(scene, doctored, _cfg(epochs=2, resume=True), progress=False)
    assert not _Evil.marker.exists()  # the pickle's os.system never ran
    # a damaged file is not resumable, not an error
    (tmp_path / "cut.pt").write_bytes((out / CHECKPOINT).read_bytes()[:500])
    assert read_checkpoint(tmp_path / "cut.pt") is None
    assert read_checkpoint(tmp_path / "missing.pt") is None
