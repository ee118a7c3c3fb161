"""Channel-parameter estimator (issue 24): CPU time per vehicle-step, and its cost vs array and subcarrier sizes.

Received pilots of real links (the ``paper`` scene traced by the closed-form source: LOS, four wall
VAs, SPs, the other car; ``--steps`` steps x 2 vehicles, noise from seed 0) are estimated with
:func:`mmslam.slam.sim.channel_estimator.nomp` at the default sizes (BS 8 x 8, vehicle 4 x 4, 256
subcarriers, pfa 0.01, <= 20 paths) and at other sizes (``--cache``: the links of a traced cache
instead, e.g. a Sionna trace with its diffuse clusters). Per size: the median and 90th percentile of
the estimation time per vehicle-step (``time.process_time``: CPU time of this process, one thread;
BLAS pinned to one thread) and the median number of estimates. Pilot synthesis is not timed.
``--estimator FILE`` times another version of the estimator module instead (e.g. the one of an
earlier commit, ``git show REV:slam/sim/channel_estimator.py > /tmp/old.py``), for an old / new
comparison on the same links and the same machine state (alternate the runs); ``--against FILE``
also runs another version on the same pilots (not timed) and prints whether every link got the same
number of estimates and the largest differences of the frequencies and amplitudes.

    OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/bench_estimator.py --steps 10
    .venv/bin/python benchmarks/bench_estimator.py --sizes default --cache CACHE --steps 10 --reps 3
    .venv/bin/python benchmarks/bench_estimator.py --sizes default --cache CACHE --against /tmp/old.py
"""
from __future__ import annotations

import argparse
import importlib.util
import json
import os
import sys
import tempfile
import time

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import numpy as np  # noqa: E402

from mmslam.raytrace.analytic import AnalyticSource  # noqa: E402
from mmslam.raytrace.cache import load_cache  # noqa: E402
from mmslam.raytrace.trace import trace_scenario  # noqa: E402
from mmslam.scenes.scenario import load_preset, with_overrides  # noqa: E402
from mmslam.slam.sim import channel_estimator as ce  # noqa: E402
from mmslam.slam.sim import estimated_sensor as es  # noqa: E402

SIZES = [(8, 4, 256), (8, 4, 128), (4, 4, 256), (4, 4, 128), (8, 4, 512), (4, 2, 256)]
"""(tx_array, rx_array, subcarriers); the first is the default."""


def run(ce, cache, steps: int, tx: int, rx: int, k: int, reps: int, against=None) -> dict:
    scn = with_overrides(cache.scenario, ["sensor.model=estimated", f"sensor.tx_array={tx}",
                                          f"sensor.rx_array={rx}", f"sensor.est_subcarriers={k}"])
    sp = scn.sensor
    pm = es.PilotModel.from_sensor(sp, scn.frequency_hz)
    rays = cache.read_rays()
    rng = np.random.default_rng(0)
    times, counts, diffs = [], [], []
    for s in range(steps):
        for v in range(cache.states.shape[1]):
            idx = np.flatnonzero((rays["step"] == s) & (rays["rx"] == v))
            st = cache.states[s, v]
            Y, _ = es.received_pilots(rays, idx, st[3], st[6], pm, rng)
            best = np.inf
            for _ in range(reps):
                t = time.process_time()
                w, g = ce.nomp(Y, pm.grid, sp.est_pfa, sp.est_max_paths)
                best = min(best, time.process_time() - t)
            times.append(best)
            counts.append(len(w))
            if against is not None:  # the other version on the same pilots: same detections, how close
                w2, g2 = against.nomp(Y, pm.grid, sp.est_pfa, sp.est_max_paths)
                same = w2.shape == w.shape
                diffs.append((same, float(np.abs(np.angle(np.exp(1j * (w - w2)))).max()) if same and len(w) else 0.0,
                              float((np.abs(g - g2) / np.abs(g2)).max()) if same and len(w) else 0.0))
    t = np.array(times) * 1e3
    if diffs:
        d = np.array(diffs)
        print(f"  against the other estimator: {int(d[:, 0].sum())} / {len(d)} links with the same number of "
              f"estimates; max |dw| {d[:, 1].max():.1e} rad, max |dg| / |g| {d[:, 2].max():.1e}", flush=True)
    return {"tx_array": tx, "rx_array": rx, "subcarriers": k, "cells": pm.grid.size,
            "median_ms": float(np.median(t)), "p90_ms": float(np.percentile(t, 90)),
            "median_estimates": float(np.median(counts)), "links": len(times)}


def _load(path: str):
    """A version of the estimator module from a file, imported as the file's stem (its numba kernels are
    cached next to it under that module name)."""
    name = os.path.splitext(os.path.basename(path))[0]
    spec = importlib.util.spec_from_file_location(name, path)
    mod = sys.modules[name] = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--steps", type=int, default=10)
    ap.add_argument("--reps", type=int, default=1, help="repetitions per link (the fastest is kept)")
    ap.add_argument("--sizes", default="all", help="'default' or 'all'")
    ap.add_argument("--estimator", default=None, help="a channel_estimator.py to time instead of this tree's")
    ap.add_argument("--against", default=None, help="a channel_estimator.py to compare the estimates with "
                    "(not timed): per link the same number of estimates, and the largest differences")
    ap.add_argument("--cache", default=None, help="a traced cache to take the links from (e.g. a Sionna trace: "
                    "diffuse clusters, ~60 rays per link); default: paper traced by the closed-form source")
    a = ap.parse_args()
    est = _load(a.estimator) if a.estimator else ce
    other = _load(a.against) if a.against else None
    print(f"estimator {a.estimator or ce.__file__}; load average {os.getloadavg()}", flush=True)
    scn = load_preset("paper")
    with tempfile.TemporaryDirectory() as tmp:
        cache = load_cache(a.cache if a.cache else
                           trace_scenario(scn, AnalyticSource(scn), tmp, steps=a.steps, progress=False))
        # compile (or load) every numba kernel once outside the timing: a two-path channel on a small grid
        g = est.Grid(2, 2, 8, 1e8)
        two = [est.atom_tensor(np.array(w), g) for w in ([0.3, -0.2, 0.5, 1.0, 0.7], [0.1, -0.1, 0.2, 1.2, 0.4])]
        est.nomp(two[0] + 0.3 * two[1], g, 0.01)
        out = []
        for tx, rx, k in (SIZES[:1] if a.sizes == "default" else SIZES):
            r = run(est, cache, a.steps, tx, rx, k, a.reps, other)
            out.append(r)
            print(f"tx {tx}x{tx} rx {rx}x{rx} K {k:4d} ({r['cells']:7d} cells): median {r['median_ms']:7.1f} ms, "
                  f"p90 {r['p90_ms']:7.1f} ms per vehicle-step, {r['median_estimates']:.0f} estimates", flush=True)
    print(f"load average {os.getloadavg()}")
    print(json.dumps(out))


if __name__ == "__main__":
    main()
