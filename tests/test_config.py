"""Config presets and the YAML schema: unknown keys name the key and suggest the nearest."""

from pathlib import Path

import pytest

from pavemap.config import dump_config, load_config, preset_config
from pavemap.errors import PavemapError


def test_presets_carry_paper_parameters():
    nus = preset_config("nuscenes")
    kit = preset_config("kitti")
    # SPEC §2: confidence threshold 0.05 nuScenes / 0.10 KITTI; τ_road 0.5; α 0.3 (Table 2).
    assert nus.fusion.tau_conf == pytest.approx(0.05)
    assert kit.fusion.tau_conf == pytest.approx(0.10)
    assert nus.fusion.tau_road == pytest.approx(0.5)
    assert nus.fusion.alpha == pytest.approx(0.3)
    assert nus.mesh.resolution == pytest.approx(0.1)
    assert nus.mesh.epochs == 7


def test_yaml_overrides_and_roundtrip(tmp_path: Path):
    f = tmp_path / "c.yaml"
    f.write_text("preset: kitti\ndevice: cpu\nfusion:\n  tau_road: 0.7\nmesh:\n  epochs: 2\n")
    cfg = load_config(f)
    assert cfg.preset == "kitti" and cfg.device == "cpu"
    assert cfg.fusion.tau_road == pytest.approx(0.7)
    assert cfg.fusion.tau_conf == pytest.approx(0.10)  # kept from the kitti preset
    assert cfg.mesh.epochs == 2
    # the dumped config loads back to the same values
    g = tmp_path / "d.yaml"
    g.write_text(dump_config(cfg))
    again = load_config(g)
    assert again.to_dict() == cfg.to_dict()


def test_unknown_key_suggests_nearest(tmp_path: Path):
    f = tmp_path / "c.yaml"
    f.write_text("fusion:\n  tau_raod: 0.7\n")
    with pytest.raises(PavemapError, match=r"unknown key 'tau_raod'.*did you mean 'tau_road'"):
        load_config(f)
    f.write_text("fuson:\n  tau_road: 0.7\n")
    with pytest.raises(PavemapError, match=r"'fuson'.*did you mean 'fusion'"):
        load_config(f)


def test_wrong_types_and_bad_presets(tmp_path: Path):
    f = tmp_path / "c.yaml"
    f.write_text("fusion:\n  tau_road: high\n")
    with pytest.raises(PavemapError, match="fusion.tau_road must be a number"):
        load_config(f)
    with pytest.raises(PavemapError, match="neither a preset"):
        load_config(tmp_path / "missing.yaml")
    f.write_text("preset: waymo\n")
    with pytest.raises(PavemapError, match="preset must be one of"):
        load_config(f)
    f.write_text("detector:\n  backend: magic\n")
    with pytest.raises(PavemapError, match="backend must be sim, yolo or file"):
        load_config(f)
