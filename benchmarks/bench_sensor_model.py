"""What the power-aware sensor model (issue 11) does to the ablation: constant vs link budget.

For each scenario (analytic trace, its path powers from Friis / Fresnel / radar equation, or a
Sionna trace with ``--source sionna``), runs
every variant over ``--mc`` seeds twice: with the paper's constant sensor model and with
``sensor.model=link`` (p_D and noise from each path's SNR; the same as ``mmslam ablate ... --set
sensor.model=link``). Under the power-aware model the filter corrects each measurement with its
own covariance (``r_scale`` times ``R_meas``); its detection probability stays the constant
``filter.p_detect_<type>``. Prints detection rates and noise stds per
landmark type, and per variant the mean vehicle position error and the mean GOSPA of the fused map
(steps >= 5). Noisy timings; a measurement, not a test.

    .venv/bin/python benchmarks/bench_sensor_model.py --scenarios paper,street --mc 3 --particles 100
"""
from __future__ import annotations

import argparse
import json
import tempfile
import time

import numpy as np

from mmslam.raytrace.analytic import AnalyticSource
from mmslam.raytrace.cache import load_cache
from mmslam.raytrace.trace import make_source, trace_scenario
from mmslam.scenes.scenario import load_preset, with_overrides
from mmslam.slam.filter import run_filter
from mmslam.slam.sim.sensor import LinkBudget, simulate_measurements
from mmslam.model import TYPE_NAMES

TYPES = {c: n for c, n in TYPE_NAMES.items() if n != "OTHER"}


def detection_stats(scn, cache, link, seed=0):
    m = simulate_measurements(scn, cache.states, cache.paths, np.random.default_rng(seed), link=link)
    out = {}
    for t, name in TYPES.items():
        n_rows = int(np.sum(cache.paths["type"] == t))
        sel = m.mask & (m.origin_type == t)
        out[name] = {"rows": n_rows, "detected": float(sel.sum() / max(n_rows, 1)),
                     "toa_std_m": float(np.sqrt(np.median(m.R_meas[sel][:, 0]))) if sel.any() else None,
                     "angle_std_rad": float(np.sqrt(np.median(m.R_meas[sel][:, 3]))) if sel.any() else None}
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--scenarios", default="paper,street")
    ap.add_argument("--variants", default="baseline,cm1,proposed")
    ap.add_argument("--mc", type=int, default=3)
    ap.add_argument("--particles", type=int, default=100)
    ap.add_argument("--processing-gain-db", type=float, default=0.0)
    ap.add_argument("--source", default="analytic", help="analytic or sionna (traced once per scenario)")
    a = ap.parse_args()
    link = LinkBudget(processing_gain_db=a.processing_gain_db)
    res = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name in a.scenarios.split(","):
            scn = load_preset(name)
            src = AnalyticSource(scn) if a.source == "analytic" else make_source(a.source, scn)
            cache = load_cache(trace_scenario(scn, src, tmp, progress=False))
            res[name] = {"detections": {"constant": detection_stats(scn, cache, None),
                                        "link": detection_stats(scn, cache, link)}}
            for model in ("constant", "link"):
                s = scn if model == "constant" else with_overrides(
                    scn, ["sensor.model=link", f"sensor.processing_gain_db={a.processing_gain_db}"])
                for v in a.variants.split(","):
                    pos, gos, t0 = [], {}, time.perf_counter()
                    for seed in range(a.mc):
                        r = run_filter(s, cache.states, cache.paths, variant=v, particles=a.particles, seed=seed)
                        k = r.vehicles["step"] >= 5
                        pos.append(float(np.sqrt(np.mean(r.vehicles["pos_err"][k] ** 2))))
                        mk = (r.metrics["map"] == "fused") & (r.metrics["step"] >= 5)
                        for t in ("VA", "SP", "VS"):
                            gos.setdefault(t, []).append(float(np.mean(r.metrics["gospa"][mk & (r.metrics["type"] == t)])))
                    res[name][f"{model}/{v}"] = {"pos_rmse_m": float(np.mean(pos)),
                                                 **{f"gospa_{t}": float(np.nanmean(g)) for t, g in gos.items()},
                                                 "wall_s": time.perf_counter() - t0}
    print(json.dumps(res, indent=1))


if __name__ == "__main__":
    main()
