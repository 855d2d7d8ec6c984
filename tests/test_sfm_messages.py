"""What SfM tells the user: only the kept path's warnings, COLMAP's solver chatter held back, no empty reasons."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from pavemap.errors import PavemapError
from pavemap.sfm.held_log import held_records, replay, warnings_of
from pavemap.sfm.result import SfmResult

SCALE_LOG = "pavemap.sfm.scale"  # a module whose warnings sfm_poses must hold back


def test_held_records_reach_the_handlers_only_when_replayed(caplog):
    caplog.set_level(logging.INFO)
    with held_records() as said:
        logging.getLogger(SCALE_LOG).warning("first %d", 1)
        logging.getLogger("pavemap.sfm.steps").info("second")
        logging.getLogger("pavemap.mesh").warning("not SfM's: passes at once")
    assert [r.getMessage() for r in caplog.records] == ["not SfM's: passes at once"]
    assert warnings_of(said) == ["first 1"]
    replay(said)
    assert [r.getMessage() for r in caplog.records][1:] == ["first 1", "second"]


def test_a_refusal_inside_the_block_still_says_what_led_to_it(caplog):
    caplog.set_level(logging.INFO)
    with pytest.raises(PavemapError), held_records():
        logging.getLogger(SCALE_LOG).warning("the reason")
        raise PavemapError("refused")
    assert [r.getMessage() for r in caplog.records] == ["the reason"]
    assert logging.getLogger("pavemap.sfm").propagate  # restored


def _path(method: str, repaired: list[int]) -> SfmResult:
    T = np.tile(np.eye(4), (6, 1, 1))
    T[:, 0, 3] = np.arange(6.0)
    return SfmResult(T, np.ones(6, bool), 1.0, 0, np.zeros((0, 3)),
                     {"method": method, "steps": {"repaired": repaired}, "scale_source": "provisional"})


@pytest.mark.parametrize("planar_measures, kept", [(5, "planar motion"), (2, "pycolmap SfM")])
def test_only_the_kept_paths_warnings_reach_the_user(monkeypatch, caplog, planar_measures, kept):
    import pavemap.sfm.pipeline as pipe

    def set_scale(res, *a, **k):  # noqa: ANN001, ANN002, ANN003
        logging.getLogger(SCALE_LOG).warning("scales of %s disagree", res.info["method"])
        res.info["road_steps"] = {"measured": 3 if res.info["method"] == "pycolmap SfM" else planar_measures}

    monkeypatch.setattr(pipe, "_set_scale", set_scale)
    monkeypatch.setattr(pipe, "planar_result", lambda *a, **k: _path("planar motion", []))
    caplog.set_level(logging.INFO)
    res = pipe._scaled_best(_path("pycolmap SfM", [2]), "auto", [], np.ones(6, bool), None, 1.5, None,
                            pipe.PartLimits(), True, True, "", None)
    other = "pycolmap SfM" if kept == "planar motion" else "planar motion"
    assert res.info["method"] == kept
    said = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
    assert said == [f"scales of {kept} disagree"]
    assert res.info["alternatives"]["warnings_of_the_path_not_kept"] == [f"scales of {other} disagree"]


def test_colmap_solver_warnings_are_held_back_unless_verbose(monkeypatch, tmp_path):
    pycolmap = pytest.importorskip("pycolmap")
    from PIL import Image

    import pavemap.sfm.pipeline as pipe
    from pavemap.types import Camera

    rng = np.random.default_rng(0)
    images = []
    for i in range(6):  # PartLimits' minimum is 5
        images.append(tmp_path / f"{i}.png")
        Image.fromarray(rng.integers(0, 255, (24, 32), dtype=np.uint8)).save(images[-1])
    seen = []

    def model(*a, **k):  # noqa: ANN002, ANN003
        seen.append(pycolmap.logging.minloglevel)
        raise PavemapError("no model")

    monkeypatch.setattr(pipe, "colmap_model", model)
    cam = Camera("c", 32, 24, np.array([[30.0, 0, 15.5], [0, 30.0, 11.5], [0, 0, 1]]))
    before = pycolmap.logging.minloglevel
    for verbose in (False, True):
        with pytest.raises(PavemapError, match="no model"):
            pipe.sfm_poses(images, cam, method="colmap", min_parallax=0, verbose=verbose)
    assert seen == [int(pycolmap.logging.ERROR), 0]
    assert pycolmap.logging.minloglevel == before


def test_ground_points_found_but_not_under_the_path_say_so(monkeypatch):
    import pavemap.sfm.scale as scale

    h = np.full(5, np.nan)
    h[2] = 1.5
    monkeypatch.setattr(scale, "road_heights", lambda *a, **k: (h.copy(), {"ground_points": 40, "observable": True,
                                                                           "reason": ""}))
    factor, _, stats = scale.refine_scale([], np.tile(np.eye(4), (5, 1, 1)), None, 1.5)
    assert np.isnan(factor)
    assert stats["reason"] == "40 road points, under only 1 of 5 cameras (need 3)"


@pytest.mark.parametrize("second_try_works", [True, False])
def test_a_failed_colmap_is_tried_once_more_on_thinned_keyframes(monkeypatch, caplog, second_try_works):
    import pavemap.sfm.pipeline as pipe

    calls = []

    def colmap_result(rec, names, keyframes, camera, camera_height, limits, hint, info):  # noqa: ANN001
        calls.append(int(keyframes.sum()))
        logging.getLogger(SCALE_LOG).warning("model of %d keyframes", keyframes.sum())
        if keyframes.all() or not second_try_works:
            raise PavemapError("SfM's steps point off the car's heading in most places")
        info["method"] = "pycolmap SfM"
        return _path("pycolmap SfM", [])

    thin = np.array([True, False, True, False, True, True, True, True])  # a creep in frames 0-4
    monkeypatch.setattr(pipe, "_colmap_result", colmap_result)
    monkeypatch.setattr(pipe, "select_keyframes", lambda imgs, parallax, mask: thin[: len(imgs)])
    monkeypatch.setattr(pipe, "planar_result", lambda *a, **k: _path("planar motion", []))
    info = {"images": 8, "keyframes": 8, "camera_height_m": 1.5}
    caplog.set_level(logging.WARNING)
    res, kf = pipe._first_path(lambda kf: object(), "auto", [f"{i}.png" for i in range(8)], [str(i) for i in range(8)],
                               np.ones(8, bool), None, 1.5, None, pipe.PartLimits(), "", info, None)
    assert calls == [8, 6]
    if second_try_works:
        assert res.info is info and info["method"] == "pycolmap SfM" and kf.tolist() == thin.tolist()
        assert info["sfm_retry"]["keyframes_before"] == 8 and info["keyframe_index"] == [0, 2, 4, 5, 6, 7]
        # the first model was replaced: only the kept one speaks on the console
        assert info["sfm_retry"]["first_try_warnings"] == ["model of 8 keyframes"]
        assert [r.getMessage() for r in caplog.records] == ["model of 6 keyframes"]
    else:
        assert res.info["method"] == "planar motion" and kf.all()
        assert "off the car's heading" in info["sfm_retry"]["failed"] and "sfm_failure" in info
        assert info["sfm_retry"]["warnings"] == ["model of 6 keyframes"]
        said = [r.getMessage() for r in caplog.records]
        assert said[0] == "model of 8 keyframes" and "model of 6 keyframes" not in said
