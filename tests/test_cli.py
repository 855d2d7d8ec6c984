"""The command line's conventions: --version, --config / --set everywhere, one-line errors, rig presets."""

from __future__ import annotations

import importlib.metadata
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from typer.testing import CliRunner

import pavemap
from pavemap.cli import app, expand_set_args


def _invoke(*args: str):
    return CliRunner().invoke(app, [str(a) for a in args])


def test_version_prints_the_package_version():
    r = _invoke("--version")
    assert r.exit_code == 0, r.output
    assert r.output.strip() == f"pavemap {pavemap.__version__}"
    assert pavemap.__version__ == importlib.metadata.version("pavemap")


def test_cli_import_does_not_load_torch():
    """--version, --help and shell completion stay fast: torch loads only when a stage runs."""
    code = "import sys, pavemap.cli; sys.exit('torch' in sys.modules)"
    assert subprocess.run([sys.executable, "-c", code]).returncode == 0


def test_expand_set_args_gives_each_pair_its_own_set():
    args = ["run", "SEQ", "--set", "fusion.hit_radius_m=0.4", "mesh.epochs=3", "--out", "r", "-s", "device=cpu",
            "filter.mask=mesh"]
    assert expand_set_args(args) == ["run", "SEQ", "--set", "fusion.hit_radius_m=0.4", "--set", "mesh.epochs=3",
                                     "--out", "r", "-s", "device=cpu", "--set", "filter.mask=mesh"]
    # a positional argument after the pairs is not swallowed; `--` ends option parsing
    assert expand_set_args(["run", "--set", "a.b=1", "SEQ"]) == ["run", "--set", "a.b=1", "SEQ"]
    assert expand_set_args(["x", "--set", "a.b=1", "--", "c.d=2"]) == ["x", "--set", "a.b=1", "--", "c.d=2"]


def test_help_lists_the_choices():
    r = _invoke("run", "--help")
    assert r.exit_code == 0
    for choice in ("auto", "sim", "yolo", "file"):
        assert choice in r.output
    for name in ("--config", "--set", "--detector", "--device", "--epochs"):
        assert name in r.output
    r = _invoke("fuse", "--help")
    assert "--set" in r.output and "--config" in r.output and "--tau-conf" not in r.output
    assert "plane" in r.output  # the --surface choices


@pytest.fixture
def captured_run(monkeypatch):
    """Replace the pipeline by a stub that writes the resolved config.yaml as the pipeline does first."""
    import pavemap.pipeline
    from pavemap.config import dump_config

    seen = {}

    class _Result:
        def summary(self) -> str:
            return "stub run"

    def fake_run(seq, cfg, out, overwrite=False, progress=True, **kw):  # noqa: ANN001, ANN003, ARG001
        Path(out).mkdir(parents=True, exist_ok=True)
        (Path(out) / "config.yaml").write_text(dump_config(cfg))
        seen["cfg"] = cfg
        return _Result()

    monkeypatch.setattr(pavemap.pipeline, "run", fake_run)
    return seen


def test_set_overrides_reach_config_yaml_and_rig_picks_kitti(tiny_seq, tmp_path, captured_run):
    out = tmp_path / "r"
    r = _invoke("run", tiny_seq.root, "--out", out, "--set", "filter.tau_road=0.6", "mesh.epochs=3",
                "--set", "fusion.association=ray output.sweep_tau_conf=0.1,0.3", "--device", "cpu")
    assert r.exit_code == 0, r.output
    written = yaml.safe_load((out / "config.yaml").read_text())
    assert written["preset"] == "kitti"  # one camera and no --config: the kitti preset ...
    assert "preset kitti" in r.output and "1 camera" in r.output  # ... and the console says why
    assert written["filter"]["tau_road"] == 0.6 and written["mesh"]["epochs"] == 3
    assert written["fusion"]["association"] == "ray" and written["output"]["sweep_tau_conf"] == [0.1, 0.3]
    assert written["device"] == "cpu"
    assert written["filter"]["tau_conf"] is None  # the preset's: the detector's operating point, which the run resolves
    assert "detector: sim" in r.output  # auto resolved: the tiny drive carries synthetic truth


def test_shortcuts_and_config_file(tiny_seq, tmp_path, captured_run):
    f = tmp_path / "c.yaml"
    f.write_text("preset: nuscenes\nmesh: {epochs: 5}\ndetector: {backend: sim, seed: 3}\n")
    r = _invoke("run", tiny_seq.root, "--out", tmp_path / "r", "--config", f, "--epochs", "2")
    assert r.exit_code == 0, r.output
    cfg = captured_run["cfg"]
    assert cfg.preset == "nuscenes" and cfg.mesh.epochs == 2 and cfg.detector.seed == 3
    r = _invoke("run", tiny_seq.root, "--out", tmp_path / "r2", "--config", "nuscenes", "--epochs", "1",
                "--set", "mesh.epochs=4")
    assert r.exit_code == 0, r.output
    assert captured_run["cfg"].mesh.epochs == 4  # --set comes after the shortcuts


def test_surround_rig_gets_nuscenes(tiny_nuscenes_seq):
    r = _invoke("config", tiny_nuscenes_seq.root, "--set", "mesh.epochs=2")
    assert r.exit_code == 0, r.output
    assert "preset nuscenes" in r.stderr and "6 cameras" in r.stderr
    cfg = yaml.safe_load(r.stdout)  # stdout is the YAML alone: `pavemap config > my.yaml` works
    assert cfg["preset"] == "nuscenes" and cfg["mesh"]["epochs"] == 2 and cfg["mesh"]["crop_m"] == 7.0


@pytest.mark.parametrize(("override", "message"), [
    ("mesh.epoch=3", "unknown key 'epoch' in section 'mesh'; did you mean 'epochs'?"),
    ("fusion.tau_road=0.6", "did you mean 'filter.tau_road'?"),
    ("mesh.epochs=three", "mesh.epochs must be an integer, got 'three'"),
    ("filter.mask=road", "filter.mask must be one of frame, mesh, both, got 'road'"),
    ("filter.tau_road=1.5", "filter.tau_road must be in [0, 1)"),
    ("output.overlay_frames=-2", "output.overlay_frames must be >= 0"),
    ("mseh.epochs=2", "did you mean 'mesh'?"),
    ("epochs", "expected section.field=value"),
])
def test_bad_set_is_one_clear_line(override, message):
    r = _invoke("config", "--config", "kitti", "--set", override)
    assert r.exit_code == 2, r.output
    lines = r.stderr.strip().splitlines()
    assert lines[-1].startswith("error: ") and message in lines[-1], r.stderr
    assert "Traceback" not in r.output


def test_bad_config_value_stops_run_before_any_stage(tiny_seq, tmp_path, captured_run):
    r = _invoke("run", tiny_seq.root, "--out", tmp_path / "r", "--set", "fusion.alpha=2")
    assert r.exit_code == 2 and "fusion.alpha" in r.stderr
    assert "cfg" not in captured_run and not (tmp_path / "r").exists()


@pytest.mark.parametrize("command", [
    ["run"], ["demo"], ["config"], ["info"], ["synth"], ["detect"], ["reconstruct"], ["fuse"], ["eval"], ["compare"],
    ["train-detector"], ["import", "folder"], ["import", "video"], ["import", "kitti"], ["import", "nuscenes"],
    ["import", "gps"],
])
def test_every_command_help_renders(command):
    # rich markup in a docstring (e.g. "[/x]") crashes --help at render time only
    r = _invoke(*command, "--help")
    assert r.exit_code == 0, r.output
    assert "Usage" in r.output
