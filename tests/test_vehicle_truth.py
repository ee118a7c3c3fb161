"""The truth of a vehicle's own maps (``slam/eval/evaluation.py``): what the vehicle could have detected so far and,
after a downlink of the fused map, everything some vehicle could have detected by the step of that downlink."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from mmslam.slam.eval.evaluation import first_seen, merge_seen, truth_union

GOLDEN = Path(__file__).resolve().parent / "golden"


def _keys(points: np.ndarray) -> list[tuple[float, ...]]:
    return sorted(map(tuple, np.asarray(points, float).tolist()))


def test_truth_union_by_hand():
    """Own landmarks count from their first sighting up to ``k``, the fused map's up to the downlink step; one seen by
    both counts once; no downlink yet (-1): the vehicle's own."""
    a, b, c, d = [0.0, 0.0, 1.0], [1.0, 0.0, 1.0], [2.0, 0.0, 1.0], [3.0, 0.0, 1.0]
    own = {"a": (2, np.array(a)), "b": (5, np.array(b))}
    fused = {"a": (1, np.array(a)), "c": (3, np.array(c)), "d": (7, np.array(d))}
    assert _keys(truth_union(own, fused, 4, -1)) == [tuple(a)]
    assert _keys(truth_union(own, fused, 4, 3)) == [tuple(a), tuple(c)]
    assert _keys(truth_union(own, fused, 6, 7)) == [tuple(a), tuple(b), tuple(c), tuple(d)]
    assert _keys(truth_union(own, fused, 1, 2)) == [tuple(a)]  # "a" through the fused map, before its own sighting
    assert truth_union({}, {}, 3, 3).shape == (0, 3)


def test_vehicle_rows_count_the_fused_truth_from_each_downlink():
    """On the stored canyon trace (city defaults, proposed, P = 30): every vehicle row's VA truth count equals the
    union, computed here from ``first_seen`` and the fusion schedule, of the vehicle's own sightings up to the step
    and every vehicle's up to its last downlink before it; rows before a vehicle's first downlink count its own
    alone, and after the downlinks some vehicle's count is larger than its own (the test is not vacuous)."""
    sys.path.insert(0, str(GOLDEN))
    try:
        import make_golden as mg
    finally:
        sys.path.remove(str(GOLDEN))
    from mmslam.slam.filter import CooperativeRun
    from mmslam.slam.filter.run import schedule
    from mmslam.slam.specs.landmarks import VA_SPEC

    scn = mg.canyon()
    states, paths = mg.load_paths(GOLDEN / "city_paths.npz")
    run = CooperativeRun(scn, states, paths, "proposed", 30, 0)
    m = run.run().metrics
    steps, n_veh = run.steps, states.shape[1]
    seen = first_seen(paths, n_veh, steps, states[:steps, :, 0:3], scn.sensor, float(scn.evaluation.va_resolution))
    own_all = seen[VA_SPEC.code]
    every = merge_seen(own_all)
    ups = schedule(scn, n_veh, steps)
    mp, ty, st = np.asarray(m["map"]).astype(str), np.asarray(m["type"]).astype(str), np.asarray(m["step"])
    larger = 0
    for n, name in enumerate(scn.vehicle_names):
        for k in range(steps):
            row = np.nonzero((mp == name) & (ty == "VA") & (st == k))[0]
            assert row.size == 1
            last = max((u for u in ups[n] if u < k), default=-1)
            own = {q for q, (s, _) in own_all[n].items() if s <= k}
            want = own | {q for q, (s, _) in every.items() if s <= last}
            assert int(m["n_true"][row[0]]) == len(want), (name, k)
            larger += len(want) > len(own)
    assert larger > 0
