"""A cache stores its scenario with every parameter resolved; the parameters the scenario left open must
follow the installed mmslam's defaults when the cache is read back (not the defaults of the mmslam that
traced it), while what the scenario set, the trace parameters and in-memory overrides are kept."""
from __future__ import annotations

import copy
import json
from pathlib import Path

import pytest

from mmslam.cli import main
from mmslam.raytrace.cache import load_cache
from mmslam.scenes.scenario import (default_settings, load_preset, refresh_settings, scenario_from_resolved,
                                    scenario_settings)


def _old_defaults(**changes: object) -> dict:
    """This version's defaults with some ``section.key`` values as an older mmslam had them."""
    d = default_settings()
    for key, v in changes.items():
        s, k = key.split("__", 1)
        node = d[s]
        *head, last = k.split("__")
        for h in head:
            node = node[h]
        node[last] = v
    return d


def test_open_parameters_take_the_current_defaults_and_set_ones_stay() -> None:
    c = load_preset("canyon")  # a city preset: no [filter] / [fusion] tables
    stored = c.to_dict()
    stored["filter"]["pd_model"] = "fixed"  # what an older mmslam resolved (its defaults)
    stored["fusion"]["aa_weights"] = "equal"
    old = _old_defaults(filter__pd_model="fixed", fusion__aa_weights="equal")
    scn, changed = refresh_settings(stored, scenario_settings(c), old)
    assert scn.filter.pd_model == "beta" and scn.fusion.aa_weights == "visibility"  # today's defaults
    assert changed == ['filter.pd_model: "fixed" -> "beta"', 'fusion.aa_weights: "equal" -> "visibility"']
    assert scenario_from_resolved(stored).filter.pd_model == "fixed"  # what was read before
    assert scn.geometry_hash() == c.geometry_hash()


def test_a_published_configuration_keeps_every_value_its_file_sets() -> None:
    p = load_preset("paper")  # sets pd_model = "fixed", aa_weights = "equal", VA p_detect 0.95, ...
    old = _old_defaults(filter__pd_model="fixed", fusion__aa_weights="equal", filter__types__VA__p_detect=0.95)
    scn, changed = refresh_settings(p.to_dict(), scenario_settings(p), old)
    assert changed == []
    assert scn.to_dict() == p.to_dict()


def test_in_memory_overrides_trace_parameters_and_old_flat_keys_are_kept() -> None:
    c = load_preset("canyon")
    stored = c.to_dict()
    stored["filter"]["merge"] = 4.0  # differs from that mmslam's default (49): set in memory, keep it
    stored["filter"]["types"]["VA"]["threshold"] = 0.3
    stored["sensor"]["fov_range"] = 80.0  # a trace parameter: it shaped the paths
    old = _old_defaults(sensor__fov_range=80.0, filter__types__VA__threshold=0.3)
    settings = {"filter": {"threshold_va": 0.3}}  # the old flat alias of filter.types.VA.threshold
    stored_scn = scenario_from_resolved(stored)
    scn, changed = refresh_settings(stored, settings, old)
    assert scn.filter.merge == 4.0 and scn.sensor.fov_range == 80.0
    assert scn.filter.types["VA"].threshold == 0.3
    assert changed == [] and scn.geometry_hash() == stored_scn.geometry_hash()


def test_a_cache_traced_before_the_heavy_tail_runs_with_todays_va_row() -> None:
    """A cache of session 19 stores the VA row without ``tail_weight`` and with that mmslam's gate 9: read back, it
    gets today's VA defaults (tail 0.2, gate 6), and says so for the gate; ``paper``, whose file now pins the
    tail at 0 and the gate at 49, keeps both."""
    c = load_preset("canyon")
    stored = c.to_dict()
    del stored["filter"]["types"]["VA"]["tail_weight"]
    stored["filter"]["types"]["VA"]["merge"] = 9.0
    old = _old_defaults(filter__types__VA__merge=9.0)
    del old["filter"]["types"]["VA"]["tail_weight"]
    scn, changed = refresh_settings(stored, scenario_settings(c), old)
    va = scn.filter.type_params("VA")
    assert (va.tail_weight, va.tail_scale, va.merge) == (0.2, 4.0, 6.0)
    assert changed == ["filter.types.VA.merge: 9.0 -> 6.0"]
    p = load_preset("paper")
    stored = p.to_dict()
    del stored["filter"]["types"]["VA"]["tail_weight"]
    scn, changed = refresh_settings(stored, {}, old, preset="paper")
    assert scn.filter.type_params("VA").tail_weight == 0.0 and scn.filter.type_params("VA").merge == 49.0


def test_without_recorded_defaults_the_stored_scenario_is_used_unchanged() -> None:
    c = load_preset("canyon")
    stored = c.to_dict()
    stored["filter"]["pd_model"] = "fixed"
    scn, changed = refresh_settings(stored, None, None)
    assert scn.filter.pd_model == "fixed" and changed == []


def test_a_damaged_settings_record_falls_back_to_the_stored_scenario() -> None:
    c = load_preset("canyon")
    stored = c.to_dict()
    stored["filter"]["pd_model"] = "fixed"
    for defaults, settings in (({"filter": "x"}, {}), (default_settings(), {"filter": 3}), ("x", None)):
        scn, changed = refresh_settings(stored, settings, defaults)  # no traceback
        assert isinstance(changed, list)
        assert scn.filter.pd_model in ("fixed", "beta")
    scn, changed = refresh_settings(stored, None, {"filter": "x"})
    assert scn.filter.pd_model == "fixed" and changed == []


def _trace(tmp_path: Path) -> Path:
    assert main(["trace", "canyon", "--source", "analytic", "--steps", "3", "--out", str(tmp_path / "c")]) == 0
    (d,) = [p for p in (tmp_path / "c").iterdir() if p.is_dir()]
    return d


def _edit_manifest(d: Path, fn) -> None:  # noqa: ANN001
    p = d / "manifest.json"
    m = json.loads(p.read_text())
    fn(m)
    p.write_text(json.dumps(m))


def test_slam_on_a_cache_of_an_older_mmslam_uses_todays_defaults_and_says_so(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    d = _trace(tmp_path)
    m = json.loads((d / "manifest.json").read_text())
    assert m["settings_defaults"] == default_settings() and m["scenario_settings"] == {}

    def older(m: dict) -> None:  # as a cache traced when the default p_D model was "fixed"
        m["resolved_scenario"]["filter"]["pd_model"] = "fixed"
        m["settings_defaults"]["filter"]["pd_model"] = "fixed"

    _edit_manifest(d, older)
    assert load_cache(d).scenario.filter.pd_model == "beta"
    capsys.readouterr()
    assert main(["slam", str(d), "--particles", "10", "--steps", "2", "--out", str(tmp_path / "r")]) == 0
    out = capsys.readouterr().out
    assert 'filter.pd_model: "fixed" -> "beta"' in " ".join(out.split())
    meta = json.loads((tmp_path / "r" / "meta.json").read_text())
    assert meta["settings_from_defaults"] == ['filter.pd_model: "fixed" -> "beta"']


def test_slam_on_a_cache_that_records_no_settings_says_which_settings_it_runs_with(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    d = _trace(tmp_path)

    def before_the_record(m: dict) -> None:
        del m["settings_defaults"], m["scenario_settings"]
        m["resolved_scenario"]["filter"]["pd_model"] = "fixed"

    _edit_manifest(d, before_the_record)
    c = load_cache(d)
    assert c.scenario.filter.pd_model == "fixed" and not c.settings_known
    capsys.readouterr()
    assert main(["slam", str(d), "--particles", "10", "--steps", "2", "--out", str(tmp_path / "r")]) == 0
    assert "does not record which settings its scenario set" in " ".join(capsys.readouterr().out.split())
    untouched = copy.deepcopy(json.loads((d / "manifest.json").read_text()))
    assert "settings_defaults" not in untouched  # reading a cache never rewrites it


def _before_body_keys(p):
    """``p``'s stored scenario, recorded tables and defaults as an mmslam without ``filter.vs_body_model`` and
    ``filter.vs_birth_height`` wrote them (the paper preset pins both since)."""
    new = ("vs_body_model", "vs_birth_height", "vs_body")
    stored = p.to_dict()
    rec = scenario_settings(p)
    old = default_settings()
    for d in (stored["filter"], rec["filter"], old["filter"]):
        for k in new:
            d.pop(k, None)
    return stored, rec, old


def test_a_cache_of_a_preset_takes_the_keys_the_preset_added_since() -> None:
    """An old cache of `paper` (traced before the preset pinned the paper's point VS): the keys the preset sets
    now and the cache's record lacks take the preset's values, not the new city defaults; a file of the
    same name whose tables differ from the preset's keeps the defaults."""
    stored, rec, old = _before_body_keys(load_preset("paper"))
    scn, changed = refresh_settings(stored, rec, old, preset="paper")
    assert scn.filter.vs_body_model == "point" and scn.filter.vs_birth_height == 1e4
    assert sorted(changed) == ['filter.vs_birth_height: (none) -> 10000.0', 'filter.vs_body_model: (none) -> "point"']
    scn, _ = refresh_settings(stored, rec, old)  # no preset named: the defaults, as before
    assert scn.filter.vs_body_model == "auto" and scn.filter.vs_birth_height == 3.0
    mine = copy.deepcopy(rec)
    mine["filter"]["r_scale"] = 1.0  # a user's file called "paper" with its own filter table
    stored["filter"]["r_scale"] = 1.0
    scn, _ = refresh_settings(stored, mine, old, preset="paper")
    assert scn.filter.vs_body_model == "auto" and scn.filter.r_scale == 1.0
