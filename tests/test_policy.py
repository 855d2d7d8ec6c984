"""The maintenance policy (issue 16): YAML checks, severity levels, certainty, lane position, urgency, ranks."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import yaml
from shapely.geometry import Point

from pavemap.config import load_config
from pavemap.errors import PavemapError
from pavemap.maintain import assess_instances
from pavemap.maintain.policy import (
    BUILTIN_POLICY,
    PRIORITIES,
    certainty,
    lane_position,
    lane_positions,
    load_policy,
    policy_from_dict,
    priority_ranks,
    severity_level,
    severity_of,
    urgency,
)
from pavemap.types import DefectInstance

BUILTIN = yaml.safe_load(BUILTIN_POLICY.read_text(encoding="utf-8"))


def _write(tmp_path, data, name="city.yaml"):
    p = tmp_path / name
    p.write_text(yaml.safe_dump(data), encoding="utf-8")
    return p


def _changed(path: tuple, value):
    d = copy.deepcopy(BUILTIN)
    node = d
    for k in path[:-1]:
        node = node[k]
    if value is None:
        del node[path[-1]]
    else:
        node[path[-1]] = value
    return d


def test_builtin_policy_loads_with_every_class():
    pol = load_policy()
    assert set(pol.severity) == {0, 1, 2, 3} and pol.severity[3].measure == "depth_max_mm"
    assert pol.fallback[3].measure == "area_m2"
    assert load_policy("") is pol  # cached: the built-in once


@pytest.mark.parametrize("path, value, message", [
    (("severity", "D40", "bands", "medium"), [20, 50], r"bands 'low' \[0, 25\) and 'medium' \[20, 50\) overlap"),
    (("severity", "D40", "bands", "medium"), [30, 50], r"gap between bands 'low' \[0, 25\) and 'medium' \[30, 50\)"),
    (("severity", "D40", "bands", "medium"), None, "missing band 'medium'"),
    (("severity", "D00", "bands", "high"), [3.0, 10.0], "band 'high' ends at 10; the last band must end at .inf"),
    (("severity", "D20", "bands", "low"), [0.5, 1.0], r"band 'low' starts at 0.5; .*values in \[0, 0.5\) have no band"),
    (("severity", "D10", "bands", "low"), [0, 0], "empty band"),
    (("severity", "D50"), {"measure": "area_m2", "bands": {}}, "unknown class 'D50'"),
    (("severity", "D20"), None, "missing class 'D20'"),
    (("urgency", "priority", "schedule"), [1.0, 2.4], "overlap"),
    (("severity", "D40", "bands", "severe"), [60, 80], "unknown band 'severe'"),
    (("lanes", "lane_width_m"), "wide", "lanes.lane_width_m: must be a number"),
    (("segments", "grades"), [40, 55, 70, 85], "must decrease"),
])
def test_bad_policy_is_a_clear_error_naming_file_and_band(tmp_path, path, value, message):
    p = _write(tmp_path, _changed(path, value))
    with pytest.raises(PavemapError, match=message) as e:
        load_policy(p)
    assert str(p) in str(e.value)
    assert f"{path[0]}." in str(e.value) or f"{path[0]}:" in str(e.value)  # names the section


def test_bad_policy_files(tmp_path):
    with pytest.raises(PavemapError, match="maintenance policy not found"):
        load_policy(tmp_path / "none.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("severity: [unclosed", encoding="utf-8")
    with pytest.raises(PavemapError, match="invalid YAML"):
        load_policy(bad)
    with pytest.raises(PavemapError, match="missing section 'urgency'"):
        policy_from_dict(_changed(("urgency",), None), "x.yaml")


def test_a_city_policy_replaces_the_builtin(tmp_path):
    d = _changed(("severity", "D40", "bands"), {"low": [0, 10], "medium": [10, 30], "high": [30, float("inf")]})
    pol = load_policy(_write(tmp_path, d))
    assert severity_level("D40", {"depth_max_mm": 35.0}, pol) == "high"
    assert severity_level("D40", {"depth_max_mm": 35.0}) == "medium"  # the built-in


@pytest.mark.parametrize("cls, measures, level", [
    (3, {"depth_max_mm": 0.0}, "low"), (3, {"depth_max_mm": 24.99}, "low"), (3, {"depth_max_mm": 25.0}, "medium"),
    (3, {"depth_max_mm": 49.9}, "medium"), (3, {"depth_max_mm": 50.0}, "high"), (3, {"depth_max_mm": -3.0}, "low"),
    ("D40", {"depth_m": 0.025}, "medium"), ("D40", {"depth_m": 0.0899}, "high"),  # truth records: metres
    ("D40", {"depth_max_m": 0.0499, "depth_m": 0.06}, "medium"),  # the carved surface's depth first
    (3, {"depth_max_mm": None, "area_m2": 0.05}, "low"), (3, {"depth_max_mm": float("nan"), "area_m2": 0.2}, "medium"),
    (3, {"area_m2": 0.45}, "high"),  # no measurable depth: the area decides
    (0, {"crack_length_m": 1.49}, "low"), (0, {"crack_length_m": 1.5}, "medium"), (1, {"length_m": 3.0}, "high"),
    (0, {"crack_length_m": 1.0, "length_m": 5.0}, "low"),  # the skeleton length before the extent
    (2, {"area_m2": 0.99}, "low"), (2, {"area_m2": 1.0}, "medium"), (2, {"area_m2": 2.5}, "high"),
])
def test_levels_at_band_edges(cls, measures, level):
    assert severity_level(cls, measures) == level


def test_severity_names_the_measure_used_and_missing_ones_raise():
    assert severity_of(3, {"depth_max_mm": None, "area_m2": 0.2})[1:] == ("area_m2", 0.2)
    assert severity_of(3, {"depth_m": 0.06, "area_m2": 0.2})[1:] == ("depth_max_mm", pytest.approx(60.0))
    with pytest.raises(PavemapError, match="D20: no severity measure"):
        severity_level(2, {"length_m": 1.0})
    with pytest.raises(PavemapError, match="unknown defect class"):
        severity_level("D99", {"area_m2": 1.0})


def test_certainty_from_probability_and_observations():
    assert certainty(0.9, 12) == "confirmed"
    assert certainty(0.45, 5) == "confirmed"
    assert certainty(0.35, 12) == "probable"  # many sightings, but a weak fused probability
    assert certainty(0.9, 2) == "probable"
    assert certainty(0.99, 1) == "single sighting"


def test_lane_position_from_the_offset():
    # offset 0 = the driven lane's centre; wheel paths at +-0.9 m; the next lane's centre at +-3.5 m
    pos = lane_positions(np.array([0.0, 0.45, 0.6, 0.9, -1.2, 1.4, -1.7, 3.5, 3.5 + 0.9, -3.5 - 1.5]))
    assert list(pos) == ["lane centre", "lane centre", "wheel path", "wheel path", "wheel path", "edge", "edge",
                         "lane centre", "wheel path", "edge"]
    assert lane_position(3.0, lane_width_m=3.0) == "lane centre"  # the neighbour lane of a 3 m lane
    assert lane_position(3.0) == "wheel path"  # 0.5 m from the next lane's centre


def test_urgency_deep_pothole_in_a_wheel_path_outranks_a_shallow_one_at_the_edge():
    deep = urgency(3, severity_level(3, {"depth_max_mm": 70}), {"area_m2": 0.3}, "wheel path")
    shallow = urgency(3, severity_level(3, {"depth_max_mm": 15}), {"area_m2": 0.3}, "edge")
    assert deep[0] == "repair now" and shallow[0] == "monitor" and deep[1] > shallow[1]
    # each factor on its own raises the score: position, severity, size, class
    base = urgency(3, "medium", {"area_m2": 0.1}, "lane centre")[1]
    assert urgency(3, "medium", {"area_m2": 0.1}, "wheel path")[1] > base
    assert urgency(3, "high", {"area_m2": 0.1}, "lane centre")[1] > base
    assert urgency(3, "medium", {"area_m2": 0.4}, "lane centre")[1] > base
    assert urgency(0, "medium", {"crack_length_m": 0.1 * 4 / 0.5}, "lane centre")[1] < base
    with pytest.raises(PavemapError, match="unknown lane position"):
        urgency(3, "high", {}, "shoulder")


def test_priority_ranks_unique_and_sorted():
    rng = np.random.default_rng(0)
    n = 40
    prio = [PRIORITIES[k] for k in rng.integers(0, 3, n)]
    score = np.round(rng.uniform(0, 4, n), 1).tolist()  # ties on purpose: the id decides
    ids = rng.permutation(n).tolist()
    ranks = priority_ranks(prio, score, ids)
    assert sorted(ranks) == list(range(1, n + 1))
    by_rank = sorted(range(n), key=lambda i: ranks[i])
    keys = [(PRIORITIES.index(prio[i]), -score[i], ids[i]) for i in by_rank]
    assert keys == sorted(keys)


def _inst(i, cls, x, y, area, prob=0.8, obs=6, **extra):
    return DefectInstance(id=i, cls=cls, polygon=Point(x, y).buffer(0.3), severity_mean=0.5, severity_max=0.6,
                          confidence=0.7, observations=obs, probability=prob, area_m2=area, length_m=1.0,
                          centroid=(x, y), priority="unassessed", extra=dict(extra))


def test_assess_instances_sets_the_record_and_sorts_by_urgency():
    route = np.column_stack([np.linspace(0, 50, 11), np.zeros(11)])
    items = [_inst(1, 3, 10.0, -1.6, 0.3, depth_max_mm=15.0, measurable=True),  # shallow, at the edge
             _inst(2, 3, 20.0, 0.9, 0.3, depth_max_mm=70.0, measurable=True),  # deep, in the left wheel path
             _inst(3, 3, 30.0, 0.0, 0.2, depth_max_mm=None, measurable=False, measure_note="unobserved ground"),
             _inst(4, 0, 40.0, -0.9, 0.2, prob=0.3, obs=1, crack_length_m=3.4)]
    assess_instances(items, route)
    ex = {i.id: i.extra for i in items}
    assert [i.priority for i in items] == ["monitor", "repair now", "schedule", "repair now"]
    assert ex[2]["priority_rank"] == 1 and ex[1]["priority_rank"] == 4
    assert ex[2]["lane_position"] == "wheel path" and ex[1]["lane_position"] == "edge"
    assert ex[2]["chainage_m"] == pytest.approx(20.0) and ex[1]["offset_m"] == pytest.approx(-1.6)
    assert ex[3]["severity_level"] == "medium" and "unobserved ground; severity from area_m2" in ex[3]["measure_note"]
    assert ex[4]["certainty"] == "single sighting" and ex[2]["certainty"] == "confirmed"
    assert sorted(e["priority_rank"] for e in ex.values()) == [1, 2, 3, 4]


def test_maintenance_config_section(tmp_path):
    cfg = load_config(None, overrides=["maintenance.segment_m=50", "maintenance.lane_width_m=3.2"])
    assert cfg.maintenance.segment_m == 50.0 and cfg.maintenance.lane_width_m == 3.2
    assert cfg.to_dict()["maintenance"] == {"policy": "", "segment_m": 50.0, "lane_width_m": 3.2,
                                            "floor_sweep": False}
    assert load_config(None, overrides=["maintenance.floor_sweep=true"]).maintenance.floor_sweep is True
    with pytest.raises(PavemapError, match="maintenance.segment_m must be"):
        load_config(None, overrides=["maintenance.segment_m=-5"])
    bad = _write(tmp_path, _changed(("severity", "D40", "bands", "medium"), [20, 50]))
    with pytest.raises(PavemapError, match="overlap"):
        load_config(None, overrides=[f"maintenance.policy={bad}"])
