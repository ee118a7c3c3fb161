"""One car, step by step, with its VA measurements and with them ignored: where a VA map helps or misleads.

Usage (one process)::

    python benchmarks/va_trace.py CACHE_DIR --seed 1006 --car 0 [--particles 300] [--variant proposed]
        [--kmin 10] [--set section.key=value ...]

Runs the variant twice on the cache, stage by stage (:class:`mmslam.slam.filter.run.CooperativeRun`): once with
every path type, once with the VA paths dropped (``city_va.py --ignore-va``). Per step it prints the car's
position error (estimate minus truth, m, world x and y), its heading error (rad) and clock-bias error (m) in both
runs, the effective sample size of its particles before resampling (of ``--particles``), whether it has a
line-of-sight path in the cache, and the true VAs it has a path to (their x, y in m). Last, the position RMSE of
both runs over ``k >= kmin`` and their difference. docs/city-slam.md quotes these traces (seeds 1006 and 1031 of
canyon, 1021 of etoile2).
"""
from __future__ import annotations

import argparse
import sys

import numpy as np


def step_line(k: int, err_va: np.ndarray, err_no: np.ndarray, ess_va: float, ess_no: float, los: bool,
              vas: np.ndarray) -> str:
    """One step's line. ``err_*``: ``(7,)`` estimate minus truth of the state (heading wrapped to (-pi, pi]);
    ``vas``: ``(n, 2)`` x, y (m) of the true VAs the car has a path to."""
    def part(e: np.ndarray, ess: float) -> str:
        return f"({e[0]:+6.2f}, {e[1]:+6.2f}) dh {e[3]:+.4f} db {e[6]:+5.2f} ess {ess:5.1f}"

    seen = " ".join(f"({x:.1f}, {y:.1f})" for x, y in vas) or "-"
    return (f"k {k:3d} {'LOS ' if los else 'NLOS'}  VA map {part(err_va, ess_va)} | VAs ignored {part(err_no, ess_no)}"
            f" | VAs seen: {seen}")


def seed_arg(s: str) -> int:
    """``--seed``: a run seed, an integer >= 0 (argparse's one-line error otherwise)."""
    try:
        v = int(s)
    except ValueError:
        v = -1
    if v < 0:
        raise argparse.ArgumentTypeError(f"{s!r}: expected a seed, an integer >= 0")
    return v


def main(argv: list[str] | None = None) -> int:
    sys.path.insert(0, str(__import__("pathlib").Path(__file__).parent))
    from city_va import nlos_mask  # noqa: PLC0415 (the same line-of-sight rule as its rmse_nlos)

    from mmslam.model import wrap_angle
    from mmslam.raytrace.cache import load_cache
    from mmslam.scenes.scenario import with_overrides
    from mmslam.slam.filter.precompile import ensure_compiled
    from mmslam.slam.filter.run import CooperativeRun
    from mmslam.slam.specs.landmarks import VA_SPEC, landmark_types

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("cache")
    ap.add_argument("--seed", type=seed_arg, required=True)
    ap.add_argument("--car", type=int, required=True, help="vehicle index (0-based)")
    ap.add_argument("--particles", type=int, default=300)
    ap.add_argument("--variant", default="proposed")
    ap.add_argument("--kmin", type=int, default=10)
    ap.add_argument("--set", action="append", default=[], help="section.key=value, as city_va.py")
    a = ap.parse_args(argv)

    c = load_cache(a.cache)
    n_veh = c.states.shape[1]
    if not 0 <= a.car < n_veh:
        ap.error(f"--car {a.car}: the cache has vehicles 0..{n_veh - 1}")
    scn = with_overrides(c.scenario, a.set)
    ensure_compiled([a.variant])
    no_va = tuple(s.code for s in landmark_types() if s.code != VA_SPEC.code)
    src = c.manifest.get("source")
    runs = [CooperativeRun(scn, c.states, c.paths, a.variant, a.particles, a.seed, source=src, evaluate=False),
            CooperativeRun(scn, c.states, c.paths, a.variant, a.particles, a.seed, include_types=no_va, source=src,
                           evaluate=False)]
    p = {k: np.asarray(v) for k, v in c.paths.items()}
    mine = p["rx"].astype(int) == a.car
    nlos = nlos_mask(c.paths, runs[0].steps, n_veh)
    print(f"== {scn.name}: {a.variant}, P = {a.particles}, seed {a.seed}, car {a.car} ({scn.vehicle_names[a.car]}); "
          "errors = estimate - truth")
    sq = [[], []]
    for k in range(runs[0].steps):
        errs, ess = [], []
        for i, run in enumerate(runs):
            est = run.step(k)[a.car]
            e = est.mean - run.true[k, a.car]
            e[3] = wrap_angle(e[3])
            errs.append(e)
            ess.append(est.ess)
            if k >= a.kmin:
                sq[i].append(float(np.sum(e[0:3] ** 2)))
        now = mine & (p["step"] == k)
        los = not nlos[k, a.car]
        va = now & (p["type"] == VA_SPEC.code)
        vas = np.unique(np.stack([p["lm_x"][va], p["lm_y"][va]], -1).astype(float), axis=0)
        print(step_line(k, errs[0], errs[1], ess[0], ess[1], los, vas), flush=True)
    r = [float(np.sqrt(np.mean(s))) if s else float("nan") for s in sq]
    print(f"position RMSE over k >= {a.kmin}: VA map {r[0]:.3f} m, VAs ignored {r[1]:.3f} m, "
          f"difference {r[0] - r[1]:+.3f} m")
    return 0


if __name__ == "__main__":
    from script_entry import run

    run(main, "va_trace.py")
