"""Config presets and the schema derived from the field types: unknown keys name the key and suggest the nearest."""

import dataclasses
import re
import typing
from pathlib import Path
from typing import Literal

import pytest

from pavemap.config import (
    SECTIONS,
    RunConfig,
    coerce,
    dump_config,
    field_types,
    load_config,
    parse_overrides,
    preset_config,
    preset_for,
)
from pavemap.detect.backends import resolve_tau_conf
from pavemap.errors import PavemapError


def test_presets_carry_paper_parameters():
    nus = preset_config("nuscenes")
    kit = preset_config("kitti")
    # SPEC §2: confidence threshold 0.05 nuScenes / 0.10 KITTI; τ_road 0.5; α 0.3 (Table 2). The threshold is
    # the detector's: none in the preset, the paper's for the simulated detector (tests/test_tau_conf.py)
    assert nus.filter.tau_conf is None and kit.filter.tau_conf is None
    assert resolve_tau_conf(nus.filter.tau_conf, nus.preset, None)[0] == pytest.approx(0.05)
    assert resolve_tau_conf(kit.filter.tau_conf, kit.preset, None)[0] == pytest.approx(0.10)
    assert nus.filter.tau_road == pytest.approx(0.5)
    assert nus.fusion.alpha == pytest.approx(0.3)
    assert nus.mesh.resolution == pytest.approx(0.1)
    # SPEC §1's 7 Adam epochs are a departure: 0 by default, the closed-form fits carry stage 1 (README)
    assert nus.mesh.epochs == 0 and kit.mesh.epochs == 0


def test_yaml_overrides_and_roundtrip(tmp_path: Path):
    f = tmp_path / "c.yaml"
    f.write_text("preset: kitti\ndevice: cpu\nfilter:\n  tau_road: 0.7\nmesh:\n  epochs: 2\n")
    cfg = load_config(f)
    assert cfg.preset == "kitti" and cfg.device == "cpu"
    assert cfg.filter.tau_road == pytest.approx(0.7)
    assert cfg.filter.tau_conf is None  # kept from the kitti preset: the detector's operating point
    assert cfg.mesh.epochs == 2
    # the dumped config loads back to the same values
    g = tmp_path / "d.yaml"
    g.write_text(dump_config(cfg))
    again = load_config(g)
    assert again.to_dict() == cfg.to_dict()


def test_unknown_key_suggests_nearest(tmp_path: Path):
    f = tmp_path / "c.yaml"
    f.write_text("filter:\n  tau_raod: 0.7\n")
    with pytest.raises(PavemapError, match=r"unknown key 'tau_raod'.*did you mean 'tau_road'"):
        load_config(f)
    f.write_text("fuson:\n  hit_radius_m: 0.7\n")
    with pytest.raises(PavemapError, match=r"'fuson'.*did you mean 'fusion'"):
        load_config(f)
    f.write_text("fusion:\n  tau_road: 0.7\n")  # the road threshold is stage 2's now
    with pytest.raises(PavemapError, match=r"c.yaml: unknown key 'tau_road' in section 'fusion'; did you mean "
                                           r"'filter.tau_road'"):
        load_config(f)


def test_wrong_types_and_bad_presets(tmp_path: Path):
    f = tmp_path / "c.yaml"
    f.write_text("filter:\n  tau_road: high\n")
    with pytest.raises(PavemapError, match="c.yaml: filter.tau_road must be a number, got 'high'"):
        load_config(f)
    with pytest.raises(PavemapError, match="neither a preset"):
        load_config(tmp_path / "missing.yaml")
    f.write_text("preset: waymo\n")
    with pytest.raises(PavemapError, match="preset must be one of"):
        load_config(f)
    f.write_text("detector:\n  backend: magic\n")
    with pytest.raises(PavemapError, match="detector.backend must be one of auto, sim, yolo, file, got 'magic'"):
        load_config(f)
    f.write_text("fusion:\n  alpha: 1.5\n")  # range checks run at load time, before any stage
    with pytest.raises(PavemapError, match=r"c.yaml: fusion.alpha must be in \(0, 1\]"):
        load_config(f)
    f.write_text("output:\n  sweep_tau_conf: 0.1\n")
    with pytest.raises(PavemapError, match="output.sweep_tau_conf must be a list of numbers"):
        load_config(f)
    f.write_text("mesh: [1, 2]\n")
    with pytest.raises(PavemapError, match="section 'mesh' must be a mapping"):
        load_config(f)


def test_every_field_is_typed_and_its_default_fits_its_type():
    """The schema is the type hints: no Any, and each preset value passes its own field's check."""
    for preset in ("nuscenes", "kitti"):
        cfg = preset_config(preset)
        for section in SECTIONS:
            obj = getattr(cfg, section)
            for name, hint in field_types(type(obj)).items():
                assert hint is not typing.Any, f"{section}.{name} is untyped"
                value = getattr(obj, name)
                assert coerce(value, hint, f"{section}.{name}") == value
    hints = field_types(RunConfig)
    assert typing.get_origin(hints["preset"]) is Literal
    assert {f.name for f in dataclasses.fields(RunConfig)} == {"preset", "device", "skip_bad_frames", *SECTIONS}


@pytest.mark.parametrize(("hint", "text", "value"), [
    (bool, "false", False), (bool, "yes", True), (int, "3", 3), (int, "4.0", 4), (float, "1e-3", 1e-3),
    (str, "models/x.pt", "models/x.pt"), (int | None, "none", None), (int | None, "2", 2),
    (Literal["a", "b"], "b", "b"), (tuple[float, ...], "0.1,0.2", (0.1, 0.2)),
    (tuple[float, ...], "[0.1, 0.2]", (0.1, 0.2)), (list[int], "1, 2", [1, 2]), (str | None, "null", None),
])
def test_coerce_command_line_text(hint, text, value):
    assert coerce(text, hint, "s.f", text=True) == value


@pytest.mark.parametrize(("hint", "value", "message"), [
    (bool, "maybe", "s.f must be true or false"), (int, True, "s.f must be an integer"),
    (int, 2.5, "s.f must be an integer"), (float, "x", "s.f must be a number"),
    (Literal["a", "b"], "c", "s.f must be one of a, b, got 'c'"), (int | None, "x", "s.f must be an integer or none"),
    (tuple[float, ...], 0.1, "s.f must be a list of numbers"), (str, None, "s.f must be a string"),
])
def test_coerce_rejects_with_field_and_allowed_values(hint, value, message):
    with pytest.raises(PavemapError, match=re.escape(f"src: {message}")):
        coerce(value, hint, "s.f", "src", text=isinstance(value, str))


def test_text_overrides_and_load_config():
    assert parse_overrides(["a.b=1 c.d=[1, 2]", "device=cpu"]) == [("a.b", "1"), ("c.d", "[1, 2]"), ("device", "cpu")]
    cfg = load_config("kitti", overrides=["mesh.epochs=2 fusion.hit_radius_m=0.4", "detector.weights=none",
                                          "mesh.threads=2", "device=0"])
    assert cfg.mesh.epochs == 2 and cfg.fusion.hit_radius_m == 0.4 and cfg.detector.weights is None
    assert cfg.mesh.threads == 2 and cfg.device == "0" and cfg.preset == "kitti"
    with pytest.raises(PavemapError, match="--set preset=nuscenes: choose the preset with --config"):
        load_config("kitti", overrides=["preset=nuscenes"])


def test_yaml_without_preset_uses_the_given_default(tmp_path: Path):
    f = tmp_path / "c.yaml"
    f.write_text("mesh: {epochs: 1}\n")
    assert load_config(f, default_preset="kitti").preset == "kitti"
    assert load_config(f).preset == "nuscenes"


def test_preset_for_rig():
    class _Seq:
        def __init__(self, n: int):
            self.cameras = {f"cam{i}": None for i in range(n)}

    assert preset_for(_Seq(1))[0] == "kitti" and preset_for(_Seq(6))[0] == "nuscenes"


def test_stage1_runs_with_the_configured_blas_threads(monkeypatch):
    """mesh.blas_threads: 1 (the default) holds numpy's and scipy's BLAS pools at one thread during stage 1 and
    gives them back after; 0 leaves them as they are."""
    import numpy  # noqa: F401 - its BLAS pool loaded
    from threadpoolctl import threadpool_info, threadpool_limits

    import pavemap.mesh.train as train
    from pavemap.mesh.config import MeshConfig

    def pools() -> dict[str, int]:
        return {i["filepath"]: i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"}

    seen = []
    monkeypatch.setattr(train, "_reconstruct", lambda *a, **k: seen.append(pools()))
    with threadpool_limits(limits=2, user_api="blas"):
        outer = pools()  # 2 each, or 1 for a pool built single-threaded
        train.reconstruct_piece(None, None, MeshConfig())  # type: ignore[arg-type]
        train.reconstruct_piece(None, None, MeshConfig(blas_threads=0))  # type: ignore[arg-type]
        after = pools()
    assert 2 in outer.values()
    assert set(seen[0].values()) == {1} and seen[1] == outer and after == outer
    with pytest.raises(PavemapError, match="blas_threads"):
        MeshConfig(blas_threads=-1)
