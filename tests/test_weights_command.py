"""`pavemap weights list / verify / install`, the user folders (platformdirs) and the one home of the hashes."""

from __future__ import annotations

import os
import pickle
import re
import shutil
from pathlib import Path

import pytest
import torch
from typer.testing import CliRunner

from pavemap.cli import app
from pavemap.detect import backends
from pavemap.weights import registry

SHIPPED = registry.packaged_path()


@pytest.fixture
def user_dirs(tmp_path, monkeypatch):
    """XDG folders in tmp, no PAVEMAP_* overrides: what a fresh user account sees."""
    for k in ("PAVEMAP_CACHE", "PAVEMAP_WEIGHTS", "YOLO_CONFIG_DIR", "PAVEMAP_YOLO_DIR"):
        monkeypatch.delenv(k, raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xcache"))
    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path / "xdata"))
    return tmp_path


def test_user_folders_follow_platformdirs_and_env(user_dirs, monkeypatch):
    from pavemap import user_cache

    assert user_cache.user_cache_dir() == user_dirs / "xcache" / "pavemap"
    assert user_cache.install_dir() == user_dirs / "xdata" / "pavemap" / "weights"
    assert user_cache.weight_dirs() == [user_dirs / "xdata" / "pavemap" / "weights",
                                        user_dirs / "xcache" / "pavemap" / "weights"]
    monkeypatch.setenv("PAVEMAP_CACHE", str(user_dirs / "c"))
    monkeypatch.setenv("PAVEMAP_WEIGHTS", str(user_dirs / "w"))
    assert user_cache.user_cache_dir() == user_dirs / "c"
    assert user_cache.install_dir() == user_dirs / "w" and user_cache.weight_dirs()[0] == user_dirs / "w"


def test_the_model_card_quotes_the_registry_hash():
    card = (SHIPPED.parent / "MODEL_CARD.md").read_text()
    quoted = re.search(r"sha256 \| `([0-9a-f]{64})`", card).group(1)
    entry = registry.known(registry.SHIPPED_WEIGHTS)
    assert quoted == entry.sha256 == registry.sha256_of(SHIPPED)
    assert backends.SHIPPED_WEIGHTS == registry.SHIPPED_WEIGHTS


def test_list_and_verify(user_dirs):
    r = CliRunner().invoke(app, ["weights", "list"])
    assert r.exit_code == 0, r.output
    assert registry.SHIPPED_WEIGHTS in r.output and f"sha256 {registry.KNOWN[0].sha256}" in r.output
    assert re.search(r"ok\s+package\s+5\.0 MiB", r.output)
    r = CliRunner().invoke(app, ["weights", "verify"])
    assert r.exit_code == 0 and r.output.startswith("ok:"), r.output


def test_verify_fails_on_a_changed_file_and_a_missing_default(user_dirs, monkeypatch):
    bad = user_dirs / "xdata" / "pavemap" / "weights" / "espnet_p_2_q_8.pth"
    bad.parent.mkdir(parents=True)
    bad.write_bytes(b"not the published file")
    r = CliRunner().invoke(app, ["weights", "verify"])
    assert r.exit_code == 1
    assert f"{bad}: sha256" in r.output and "differs from the expected 343b0e77" in r.output
    bad.unlink()
    monkeypatch.setattr(registry, "packaged_path", lambda file=registry.SHIPPED_WEIGHTS: user_dirs / "none" / file)
    r = CliRunner().invoke(app, ["weights", "verify"])
    assert r.exit_code == 1 and f"{registry.SHIPPED_WEIGHTS}: missing" in r.output, r.output
    assert "required, MISSING" in CliRunner().invoke(app, ["weights", "list"]).output


@pytest.mark.slow
def test_install_copies_a_detector_where_runs_find_it(user_dirs, monkeypatch):
    own = user_dirs / "mine.pt"
    shutil.copyfile(SHIPPED, own)
    r = CliRunner().invoke(app, ["weights", "install", str(own)])
    assert r.exit_code == 0, r.output
    dest = user_dirs / "xdata" / "pavemap" / "weights" / "mine.pt"
    assert dest.read_bytes() == own.read_bytes() and "D00, D10, D20, D40" in r.output
    assert not [p for p in dest.parent.iterdir() if p.name.startswith(".")]  # no partial file left
    # the shipped name installed by hand is what a run falls back to when the package lacks it
    shutil.copyfile(SHIPPED, user_dirs / registry.SHIPPED_WEIGHTS)
    assert CliRunner().invoke(app, ["weights", "install", str(user_dirs / registry.SHIPPED_WEIGHTS)]).exit_code == 0
    monkeypatch.setattr(registry, "packaged_path", lambda file=registry.SHIPPED_WEIGHTS: user_dirs / "none" / file)
    assert backends.shipped_weights() == dest.parent / registry.SHIPPED_WEIGHTS


class _Evil:
    def __reduce__(self):
        return (os.system, (f"touch {_Evil.marker}",))


def test_install_refuses_what_is_not_a_yolo_checkpoint(user_dirs):
    target = user_dirs / "xdata" / "pavemap" / "weights"
    _Evil.marker = user_dirs / "pwned"
    evil = user_dirs / "evil.pt"
    torch.save({"model": _Evil()}, evil, pickle_module=pickle)
    sd = user_dirs / "state.pt"
    torch.save({"w": torch.zeros(2)}, sd)
    txt = user_dirs / "notes.txt"
    txt.write_text("hello")
    for f, why in ((evil, r"evil\.pt: not a loadable YOLO checkpoint.*posix\.system is not allowed"),
                   (sd, r"state\.pt: not a YOLO checkpoint \(no 'model' entry\)"),
                   (txt, r"notes\.txt: expected a YOLO detection checkpoint \(\.pt\)"),
                   (user_dirs / "gone.pt", r"gone\.pt: file not found")):
        r = CliRunner().invoke(app, ["weights", "install", str(f)])
        assert r.exit_code == 2, r.output
        assert re.search(why, r.output.replace("\n", " ")), r.output
    assert not _Evil.marker.exists()  # the pickle's code never ran
    assert not target.exists() or not list(target.iterdir())


def test_install_checks_a_segmenter_as_a_state_dict(user_dirs):
    fake = user_dirs / "espnet_p_2_q_8.pth"
    torch.save({"model": [1, 2]}, fake)
    r = CliRunner().invoke(app, ["weights", "install", str(fake)])
    assert r.exit_code == 2 and "not a state dict of tensors" in r.output, r.output
    real = Path(__file__).resolve().parents[2] / "shared/data/pretrained/espnet-cityscapes/espnet_p_2_q_8.pth"
    if real.is_file():
        r = CliRunner().invoke(app, ["weights", "install", str(real)])
        assert r.exit_code == 0 and "tensors" in r.output, r.output
        assert (user_dirs / "xdata" / "pavemap" / "weights" / real.name).is_file()
