"""Fused VA GOSPA and position RMSE on a traced city cache (issue 10 acceptance), per seed.

Usage (one process, nice it on a shared machine)::

    python benchmarks/city_va.py CACHE_DIR [--seeds 0-4] [--particles 300] [--kmin 10]
        [--variant proposed] [--set section.key=value ...] [--save OUT.npz]

Prints, per seed and as the mean (with the 95% Student-t half-width over seeds): the fused VA
GOSPA averaged over steps ``k >= kmin`` (m), the same for an empty map (the truth's GOSPA with no
estimates, c = evaluation.gospa_c), and the position RMSE over all vehicles and steps ``k >= kmin``
(m). ``--odometry`` also runs dead reckoning for the RMSE reference.
"""
from __future__ import annotations

import argparse
import sys
import time

import numpy as np
from scipy import stats


def seeds_of(s: str) -> list[int]:
    """``"0-4"`` -> ``[0, 1, 2, 3, 4]``; ``"1,3"`` -> ``[1, 3]``."""
    if "-" in s:
        a, b = s.split("-")
        return list(range(int(a), int(b) + 1))
    return [int(x) for x in s.split(",")]


def scores(r, kmin: int) -> dict[str, float]:
    """One run's fused VA GOSPA (m), its missed / false parts (m^2) and truth count, averaged over steps
    ``k >= kmin``, and the position RMSE (m) over all vehicles and those steps."""
    m = r.metrics
    mp, ty, st = np.asarray(m["map"]).astype(str), np.asarray(m["type"]).astype(str), np.asarray(m["step"])
    sel = (mp == "fused") & (ty == "VA") & (st >= kmin)
    g = np.asarray(m["gospa"], float)[sel]
    miss = np.asarray(m["missed"], float)[sel]
    n_true = np.asarray(m["n_true"], float)[sel]
    v = r.vehicles
    e = np.asarray(v["pos_err"], float)[np.asarray(v["step"]) >= kmin]
    return {"va": float(g.mean()), "rmse": float(np.sqrt(np.mean(e * e))), "missed": float(miss.mean()),
            "false": float(np.asarray(m["false"], float)[sel].mean()), "n_true": float(n_true.mean())}


def ci(a) -> tuple[float, float]:
    """Mean and 95% Student-t half-width over runs."""
    a = np.asarray(a, float)
    if a.size < 2:
        return float(a.mean()), float("nan")
    return float(a.mean()), float(stats.t.ppf(0.975, a.size - 1) * a.std(ddof=1) / np.sqrt(a.size))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("cache")
    ap.add_argument("--seeds", default="0-4")
    ap.add_argument("--particles", type=int, default=300)
    ap.add_argument("--kmin", type=int, default=10)
    ap.add_argument("--variant", default="proposed")
    ap.add_argument("--steps", type=int, default=None)
    ap.add_argument("--set", action="append", default=[])
    ap.add_argument("--odometry", action="store_true")
    ap.add_argument("--save", default=None)
    a = ap.parse_args(argv)
    from mmslam.slam.filter import run_slam

    rows = []
    seeds = seeds_of(a.seeds)
    for s in seeds:
        t0 = time.perf_counter()
        r = run_slam(a.cache, a.variant, a.particles, s, steps=a.steps, overrides=a.set)
        sc = scores(r, a.kmin)
        if a.odometry:
            o = run_slam(a.cache, "odometry", a.particles, s, steps=a.steps, overrides=a.set)
            so = scores(o, a.kmin)
            sc["empty"], sc["odo_rmse"] = so["va"], so["rmse"]
        rows.append(sc)
        print(f"seed {s}: fused VA GOSPA {sc['va']:.2f} m (missed^2 {sc['missed']:.1f}, false^2 {sc['false']:.1f}, "
              f"n_true {sc['n_true']:.2f})  RMSE {sc['rmse']:.3f} m"
              + (f"  empty {sc['empty']:.2f} m  odometry RMSE {sc['odo_rmse']:.3f} m" if a.odometry else "")
              + f"  [{time.perf_counter() - t0:.0f} s]", flush=True)
    for key in ("va", "rmse", "missed", "false") + (("empty", "odo_rmse") if a.odometry else ()):
        m, h = ci([r[key] for r in rows])
        print(f"mean {key}: {m:.3f} +- {h:.3f}")
    if a.save:
        np.savez(a.save, seeds=np.array(seeds), **{k: np.array([r[k] for r in rows]) for k in rows[0]})
    return 0


if __name__ == "__main__":
    sys.exit(main())
