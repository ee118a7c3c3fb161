"""City SLAM acceptance in one run (issues 10 and 22): VA map, localisation, VS of other vehicles, per seed.

Usage (one process, nice it on a shared machine)::

    python benchmarks/city_va.py CACHE_DIR [CACHE_DIR ...] [--seeds 100-109] [--particles 300] [--kmin 10]
        [--variant proposed] [--set section.key=value ...] [--odometry] [--ignore-va]
        [--compare section.key=value[,section.key=value ...]] [--known-va 0,0.3,1] [--save OUT.json]

Per cache (scene) and seed it runs ``--variant`` (default ``proposed``) with the cache's scenario and the
``--set`` overrides, and prints, averaged over steps ``k >= kmin``:

- ``va``: the fused VA GOSPA (m), its missed / false parts (m^2), the truth count, ``n_visible`` (VAs some
  vehicle could detect at that step) and ``card``, the fused VA map's PHD mass (its expected number of VAs, to
  set against the truth count); ``va_loc``: the rms distance (m) of the truths GOSPA assigned to a fused VA, pooled
  over those steps (:func:`assigned_rms`): how accurate the map is where it has a VA, a 3-D distance (a ``--known-va``
  error E is a std per axis: sqrt(3) E in 3-D);
- ``empty``: the same truth's GOSPA with no estimates (``sqrt(c^alpha / 2 n_true)`` per step; computed, no run);
- ``floor2`` (per scene): the GOSPA of a map that holds every truth VA exactly except those some vehicle could
  detect at one step only so far (:func:`mmslam.slam.eval.evaluation.unconfirmed_counts`): the floor for a filter
  that confirms a landmark from its second detection on;
- ``rmse``: the position RMSE (m) over all vehicles and those steps, and ``rmse_nlos`` over the (vehicle, step)
  pairs without a line-of-sight path in the cache (the car that lost the BS), ``rmse_nlos_va`` over those of them with
  a VA path in the cache (where a VA map can act without the BS);
- ``nees``: the median over those vehicle-steps of the horizontal position's NEES against the particle covariance
  (the vehicles table's ``pos_nees``, 2 degrees of freedom): 2 ln 2 = 1.39 for a filter whose spread matches its
  error, larger where the particle cloud is narrower than the error (the median, as a cloud collapsed to a few
  particles gives single values of 1e6 and more);
- ``vs`` / ``vs_others``: the fused VS GOSPA against every vehicle, and of the fused map's non-ego Gaussians
  against the vehicles another vehicle could see (map ``fused_others``; NaN without labels);
- ``sp`` / ``sp_false``: the fused SP GOSPA (m) and its false part (m^2): on a city scene without scatterers every
  SP is false, most of them a wall bounce taken for a scatter point at its reflection point (docs/city-slam.md);
- per scene, from the cache alone (:func:`va_path_stats`): the VA paths per vehicle-step and the share of the
  vehicle-steps without line of sight that have a VA path (what any VA map can act on).

``--known-va E1,E2,...``: the variant once per mapping error ``E`` (m) with a known VA map instead of the one it
estimates (:mod:`mmslam.slam.filter.known_map`: every vehicle given, before each correction, the true VAs it
has a path to at that step, each moved by a fixed error of std ``E``, covariance ``max(E, 0.05)^2 I``):
``known<E>_rmse`` and ``known<E>_rmse_nlos``, paired against ``--ignore-va`` (the upper bound of what a VA map
with that error helps localisation). ``--odometry``: dead reckoning too (``odo_rmse``). ``--ignore-va``: the same variant with the VA paths dropped
from the measurements (``include_types`` without VA: the filter never sees a wall bounce), ``noVA_rmse`` and
``noVA_rmse_nlos``, ``noVA_nees``. ``--compare``: the variant once more with these extra overrides (``cmp_*``). Every claimed
difference is printed as a paired mean with its 95% Student-t half-width over the seeds, with its median, the share
of seeds on which it is negative and the number on which it exceeds +0.1 (:func:`paired`). ``--seeds`` takes ranges
and lists, e.g. ``0-9,1000-1039``.
"""
from __future__ import annotations

import argparse
import json
import math
import re
import sys
import time
from collections.abc import Sequence

import numpy as np
from scipy import stats


def seeds_of(s: str) -> list[int]:
    """``"0-4"`` -> ``[0, 1, 2, 3, 4]``; ``"1,3"`` -> ``[1, 3]``; ``"0-2,10-11"`` -> ``[0, 1, 2, 10, 11]``. An empty
    or reversed range, a repeated seed (it would count twice in the paired statistics) or anything else is
    argparse's one-line error (exit 2)."""
    out: list[int] = []
    try:
        for part in s.split(","):
            a, _, b = part.partition("-")
            lo, hi = int(a), int(b if b else a)
            if hi < lo:
                raise ValueError
            out += range(lo, hi + 1)
    except ValueError:
        out = []
    if not out or len(set(out)) != len(out):
        raise argparse.ArgumentTypeError(f"{s!r}: expected seeds as ranges and numbers without repeats, e.g. 0-9,100")
    return out


def errors_of(s: str) -> list[float]:
    """``"0,0.3,1"`` -> ``[0.0, 0.3, 1.0]`` (``--known-va``); a bad list is argparse's one-line error, exit 2."""
    try:
        out = [float(x) for x in s.split(",") if x]
    except ValueError:
        out = [-1.0]
    if not out or not all(e >= 0.0 for e in out):
        raise argparse.ArgumentTypeError(f"{s!r}: expected mapping errors >= 0 in metres, e.g. 0,0.3,1")
    return out


def nlos_mask(paths: dict, steps: int, n_veh: int) -> np.ndarray:
    """``(steps, n_veh)`` bool: no line-of-sight (BS) path for that vehicle at that step."""
    from mmslam.slam.specs.landmarks import BS_SPEC

    los = np.zeros((steps, n_veh), bool)
    st, rx, ty = (np.asarray(paths[c]) for c in ("step", "rx", "type"))
    sel = (ty == BS_SPEC.code) & (st < steps)
    los[st[sel], rx[sel]] = True
    return ~los


def va_path_mask(paths: dict, steps: int, n_veh: int) -> np.ndarray:
    """``(steps, n_veh)`` bool: the vehicle has at least one VA path in the cache at that step."""
    from mmslam.slam.specs.landmarks import VA_SPEC

    has = np.zeros((steps, n_veh), bool)
    st, rx, ty = (np.asarray(paths[c]) for c in ("step", "rx", "type"))
    sel = (ty == VA_SPEC.code) & (st < steps)
    has[st[sel], rx[sel]] = True
    return has


def va_path_stats(paths: dict, steps: int, n_veh: int, kmin: int) -> tuple[float, float]:
    """What a VA map can act on, from the cache alone: ``(VA paths per vehicle-step, share of the vehicle-steps
    without a line-of-sight path that have at least one VA path)`` over steps ``kmin <= k < steps`` (NaN for a share
    with no such step). A vehicle-step without a VA path gets nothing from any VA map, known or estimated."""
    from mmslam.slam.specs.landmarks import VA_SPEC

    st, rx, ty = (np.asarray(paths[c]) for c in ("step", "rx", "type"))
    n_va = np.zeros((steps, n_veh))
    sel = (ty == VA_SPEC.code) & (st < steps)
    np.add.at(n_va, (st[sel], rx[sel]), 1.0)
    n_va, dark = n_va[kmin:], nlos_mask(paths, steps, n_veh)[kmin:]
    per_step = float(n_va.mean()) if n_va.size else math.nan
    return per_step, float(np.mean(n_va[dark] > 0)) if dark.any() else math.nan


def scores(r, kmin: int, nlos: np.ndarray, ev, nlos_va: np.ndarray | None = None) -> dict[str, float]:
    """One run's scores, averaged over steps ``k >= kmin`` (module docstring); ``ev``: ``[evaluation]``; ``nlos_va``
    ``(steps, n_veh)``: the vehicle-steps of ``rmse_nlos_va`` (without line of sight, with a VA path), or None."""
    m = r.metrics
    mp, ty, st = np.asarray(m["map"]).astype(str), np.asarray(m["type"]).astype(str), np.asarray(m["step"])
    out: dict[str, float] = {}

    def mean(col: str, map_: str, typ: str) -> float:
        sel = (mp == map_) & (ty == typ) & (st >= kmin)
        a = np.asarray(m[col], float)[sel]
        return float(a.mean()) if a.size else math.nan

    out["va"] = mean("gospa", "fused", "VA")
    out["missed"], out["false"] = mean("missed", "fused", "VA"), mean("false", "fused", "VA")
    out["n_true"], out["n_visible"] = mean("n_true", "fused", "VA"), mean("n_visible", "fused", "VA")
    out["card"] = mean("card", "fused", "VA")
    sel = (mp == "fused") & (ty == "VA") & (st >= kmin)
    n_true = np.asarray(m["n_true"], float)[sel]
    out["va_loc"] = assigned_rms(np.asarray(m["loc"], float)[sel], np.asarray(m["missed"], float)[sel], n_true, ev)
    out["empty"] = float(np.mean((ev.gospa_c ** ev.gospa_p / ev.gospa_alpha * n_true) ** (1 / ev.gospa_p))) if n_true.size else math.nan
    out["vs"], out["vs_others"] = mean("gospa", "fused", "VS"), mean("gospa", "fused_others", "VS")
    out["sp"], out["sp_false"] = mean("gospa", "fused", "SP"), mean("false", "fused", "SP")
    v = r.vehicles
    k, n = np.asarray(v["step"]), np.asarray(v["vehicle"]).astype(int)
    e = np.asarray(v["pos_err"], float)
    late = k >= kmin
    out["rmse"] = float(np.sqrt(np.mean(e[late] ** 2)))
    nl = late & nlos[k, n]
    out["rmse_nlos"] = float(np.sqrt(np.mean(e[nl] ** 2))) if nl.any() else math.nan
    if nlos_va is not None:
        nv = late & nlos_va[k, n]
        out["rmse_nlos_va"] = float(np.sqrt(np.mean(e[nv] ** 2))) if nv.any() else math.nan
    out["nlos_share"] = float(nl.sum() / max(late.sum(), 1))
    nees = np.asarray(v["pos_nees"], float)[late]
    out["nees"] = float(np.nanmedian(nees)) if np.isfinite(nees).any() else math.nan
    return out


def assigned_rms(loc: np.ndarray, missed: np.ndarray, n_true: np.ndarray, ev) -> float:
    """The fused map's accuracy where it has a landmark: ``(sum loc / sum assigned)^(1/p)`` (m; the rms distance for
    GOSPA's p = 2, every preset's) over the steps given,
    from GOSPA's own split (``slam/eval/gospa.py``): ``loc`` the summed ``dist^p`` of the truths assigned to an
    estimate within the cut-off ``c``, ``missed`` ``c^p / alpha`` per truth left unassigned, so ``n_true - missed /
    (c^p / alpha)`` truths were assigned. NaN when none was, or for ``alpha != 2`` (no such split). Arrays ``(K,)``
    per step; ``ev``: ``[evaluation]``."""
    if ev.gospa_alpha != 2.0:
        return math.nan
    assigned = float(np.sum(n_true - missed / (ev.gospa_c ** ev.gospa_p / ev.gospa_alpha)))
    return float((np.sum(loc) / assigned) ** (1.0 / ev.gospa_p)) if assigned > 0.5 else math.nan


def ci(a) -> tuple[float, float]:
    """Mean and 95% Student-t half-width over runs (NaNs dropped)."""
    a = np.asarray(a, float)
    a = a[np.isfinite(a)]
    if a.size < 2:
        return (float(a.mean()) if a.size else math.nan), math.nan
    return float(a.mean()), float(stats.t.ppf(0.975, a.size - 1) * a.std(ddof=1) / np.sqrt(a.size))


def paired(diffs: Sequence[float]) -> dict[str, float]:
    """Summary of per-seed paired differences ``x - y`` (NaNs dropped): ``n`` (the finite ones), ``mean`` and 95% t
    ``half`` width (:func:`ci`), ``median``, ``lower`` (the share of seeds with ``x < y``) and ``hurt`` (the number of
    seeds with ``x - y > 0.1``: for an RMSE, those on which ``x`` costs more than 0.1 m); NaN for no finite one."""
    a = np.asarray(diffs, float)
    a = a[np.isfinite(a)]
    mean, half = ci(a)
    if not a.size:
        return {"n": 0.0, "mean": mean, "half": half, "median": math.nan, "lower": math.nan, "hurt": math.nan}
    return {"n": float(a.size), "mean": mean, "half": half, "median": float(np.median(a)),
            "lower": float(np.mean(a < 0)), "hurt": float(np.sum(a > 0.1))}


def run_scene(cache: str, a: argparse.Namespace) -> dict:
    """All runs of one cache; prints per seed and the summary; returns the rows and summary."""
    from mmslam.raytrace.cache import load_cache
    from mmslam.slam.filter import run_slam
    from mmslam.scenes.scenario import with_overrides
    from mmslam.slam.eval.evaluation import unconfirmed_counts
    from mmslam.slam.filter.known_map import known_map
    from mmslam.slam.specs.landmarks import VA_SPEC, landmark_types

    c = load_cache(cache)
    steps = c.states.shape[0] if a.steps is None else a.steps
    n_veh = c.states.shape[1]
    nlos = nlos_mask(c.paths, c.states.shape[0], n_veh)
    nlos_va = nlos & va_path_mask(c.paths, c.states.shape[0], n_veh)  # where a VA map can act without the BS
    run_scn = with_overrides(c.scenario, a.set)  # the runs' sensor and evaluation settings (--set)
    ev = run_scn.evaluation
    no_va = tuple(s.code for s in landmark_types() if s.code != VA_SPEC.code)
    cmp_sets = [x for x in re.split(r",(?=\w+(?:\.\w+)+=)", a.compare) if x] if a.compare else []
    known_errors = a.known_va
    rows = []
    print(f"== {c.scenario.name} ({cache}), {a.variant}, P = {a.particles}, k >= {a.kmin}, --set {a.set}", flush=True)
    va_per_step, nlos_va_share = va_path_stats(c.paths, steps, n_veh, a.kmin)
    print(f"  VA paths per vehicle-step: {va_per_step:.2f}; vehicle-steps without line of sight that have one: "
          + ("none without line of sight" if math.isnan(nlos_va_share) else f"{nlos_va_share:.0%}"), flush=True)
    for s in a.seeds:
        t0 = time.perf_counter()
        sc = scores(run_slam(cache, a.variant, a.particles, s, steps=steps, overrides=a.set), a.kmin, nlos, ev, nlos_va)
        if a.odometry:
            sc["odo_rmse"] = scores(run_slam(cache, "odometry", a.particles, s, steps=steps, overrides=a.set),
                                    a.kmin, nlos, ev, nlos_va)["rmse"]
        if a.ignore_va:
            o = scores(run_slam(cache, a.variant, a.particles, s, steps=steps, include_types=no_va,
                                overrides=a.set), a.kmin, nlos, ev, nlos_va)
            sc["noVA_rmse"], sc["noVA_rmse_nlos"], sc["noVA_rmse_nlos_va"] = o["rmse"], o["rmse_nlos"], o["rmse_nlos_va"]
            sc["noVA_nees"] = o["nees"]
        if cmp_sets:
            o = scores(run_slam(cache, a.variant, a.particles, s, steps=steps, overrides=a.set + cmp_sets),
                       a.kmin, nlos, ev, nlos_va)
            sc.update({f"cmp_{k}": v for k, v in o.items()})
        for e in known_errors:
            km = known_map(c.paths, VA_SPEC.code, e, float(c.scenario.sensor.p_detect), np.random.default_rng([s, 1]))
            o = scores(run_slam(cache, a.variant, a.particles, s, steps=steps, overrides=a.set, known_map=km),
                       a.kmin, nlos, ev, nlos_va)
            for key in ("rmse", "rmse_nlos", "rmse_nlos_va"):
                sc[f"known{e:g}_{key}"] = o[key]
        sc["seed"] = s
        rows.append(sc)
        print(f"seed {s}: " + "  ".join(f"{k} {v:.3f}" for k, v in sc.items() if k != "seed")
              + f"  [{time.perf_counter() - t0:.0f} s]", flush=True)
    summ = {}
    for key in [k for k in rows[0] if k != "seed"]:
        summ[key] = ci([r[key] for r in rows])
        print(f"  mean {key}: {summ[key][0]:.3f} +- {summ[key][1]:.3f}")
    va, emp = summ["va"][0], summ["empty"][0]
    print(f"  VA / empty map: {va / emp:.3f}")
    # the truths no two-detection filter can have found (seen at one step so far): the floor of the ratio
    unconf = unconfirmed_counts(c.paths, n_veh, steps, c.states[:steps, :, 0:3], run_scn.sensor,
                                float(ev.va_resolution))[VA_SPEC.code][a.kmin:]
    floor2 = float(np.mean((ev.gospa_c ** ev.gospa_p / ev.gospa_alpha * unconf) ** (1 / ev.gospa_p))) if unconf.size else math.nan
    summ["floor2"] = (floor2, 0.0)
    summ["va_paths_per_step"], summ["nlos_with_va"] = (va_per_step, 0.0), (nlos_va_share, 0.0)
    print(f"  two-detection floor (truths seen at one step so far: {unconf.mean():.1f} per step): {floor2:.3f} m, "
          f"{floor2 / emp:.3f} of the empty map")
    pairs = []
    if a.odometry:
        pairs.append(("rmse", "odo_rmse"))
        print(f"  RMSE / odometry: {summ['rmse'][0] / summ['odo_rmse'][0]:.3f}")
    if a.ignore_va:
        pairs += [("rmse", "noVA_rmse"), ("rmse_nlos", "noVA_rmse_nlos"), ("rmse_nlos_va", "noVA_rmse_nlos_va")]
        pairs += [(f"known{e:g}_{k}", f"noVA_{k}") for e in known_errors for k in ("rmse", "rmse_nlos", "rmse_nlos_va")]
    if cmp_sets:
        pairs += [(k, f"cmp_{k}") for k in ("va", "rmse", "vs", "vs_others")]
    for x, y in pairs:
        p = paired([r[x] - r[y] for r in rows])
        summ[f"{x}-{y}"] = (p["mean"], p["half"])
        summ[f"{x}-{y} spread"] = (p["median"], p["lower"], p["hurt"])
        print(f"  paired {x} - {y}: {p['mean']:+.3f} +- {p['half']:.3f}" + ("  (beyond the spread)" if abs(p["mean"]) > p["half"] else "")
              + f"; median {p['median']:+.3f}, lower on {p['lower']:.0%} of the seeds, higher by > 0.1 on {p['hurt']:.0f}"
              + (f" (of {p['n']:.0f} seeds with a value)" if p["n"] < len(rows) else ""))
    return {"scene": c.scenario.name, "cache": cache, "rows": rows, "summary": summ}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("cache", nargs="+")
    ap.add_argument("--seeds", type=seeds_of, default="0-4")
    ap.add_argument("--particles", type=int, default=300)
    ap.add_argument("--kmin", type=int, default=10)
    ap.add_argument("--variant", default="proposed")
    ap.add_argument("--steps", type=int, default=None)
    ap.add_argument("--set", action="append", default=[])
    ap.add_argument("--odometry", action="store_true")
    ap.add_argument("--ignore-va", action="store_true")
    ap.add_argument("--compare", default="")
    ap.add_argument("--known-va", type=errors_of, default=[], help="mapping errors (m) of known VA maps, e.g. 0,0.3,1")
    ap.add_argument("--save", default=None)
    a = ap.parse_args(argv)
    if a.save:
        check_save_target(a.save)  # before any run: a refused --save loses no computation
    out = [run_scene(c, a) for c in a.cache]
    if a.save:
        from mmslam.outputs import atomic_write_bytes

        atomic_write_bytes(a.save, json.dumps(out, indent=1).encode(), fsync=False)
    return 0


def is_city_va_save(path) -> bool:
    """True if ``path`` is a file an earlier ``--save`` wrote: JSON, a list of scenes, each a dict with ``scene``,
    ``cache``, ``rows`` and ``summary`` (what :func:`run_scene` returns)."""
    try:
        with open(path, "rb") as f:
            data = json.loads(f.read())
    except (OSError, ValueError):
        return False
    return isinstance(data, list) and bool(data) and all(
        isinstance(d, dict) and {"scene", "cache", "rows", "summary"} <= set(d) for d in data)


def check_save_target(path: str) -> None:
    """``--save``: a new file in an existing folder, or one an earlier ``--save`` wrote (replaced); anything else (a
    user's file, a folder) is a one-line :class:`~mmslam.errors.MmslamError`, exit 2 (:func:`script_entry.run`)."""
    from mmslam.outputs import check_file_target

    check_file_target(path, "city_va", is_city_va_save, option="--save")


if __name__ == "__main__":
    from script_entry import run

    run(main, "city_va.py")
