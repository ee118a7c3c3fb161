"""Where the fused VA map is wrong: the error of each true VA's nearest fused Gaussian, per VA.

Usage (one process)::

    python benchmarks/va_map_error.py CACHE_DIR [--seeds 1000-1009] [--particles 300] [--kmin 10]
        [--variant proposed] [--within 3] [--min-weight 0.5] [--set section.key=value ...]

Per seed it runs the variant stage by stage (:class:`mmslam.slam.filter.run.CooperativeRun`) and, at every step
``k >= kmin``, takes the BS's fused VA map and each true VA some vehicle has a path to at that step. For each such
VA the nearest fused Gaussian of weight ``>= min-weight`` (position marginal) is *found* if it lies within
``--within`` metres; its error (estimate minus truth, m, world frame) and NEES (``e^T P^-1 e``, 3 dof: 3 on
average for a consistent map) are pooled over steps and seeds. Printed per true VA (landmark id, truth position,
distance to the BS and to the nearest other true VA of the cache), and pooled over all VAs: the share found, the mean and rms
error per axis, and the median and mean NEES; and per seed the share found and the rms error (m), to set against
that seed's localisation. ``benchmarks/city_va.py`` gives the map's GOSPA and ``va_loc``; this
says which VAs make them (docs/city-slam.md, "Where canyon's error comes from").
"""
from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass, field

import numpy as np


def nearest_errors(m: np.ndarray, w: np.ndarray, P: np.ndarray, truths: np.ndarray, within: float,
                   min_weight: float) -> tuple[np.ndarray, np.ndarray]:
    """Error and NEES of each truth's nearest Gaussian.

    Args:
        m: ``(Q, 3)`` Gaussian position means (m); ``w``: ``(Q,)`` weights; ``P``: ``(Q, 3, 3)`` position covariances.
        truths: ``(T, 3)`` true positions (m).
        within: the largest distance (m) at which a Gaussian counts as found.
        min_weight: Gaussians lighter than this are not considered.

    Returns:
        ``err (T, 3)`` estimate minus truth of the nearest Gaussian (NaN rows: none found) and ``nees (T,)``.
    """
    err = np.full((len(truths), 3), np.nan)
    nees = np.full(len(truths), np.nan)
    keep = np.asarray(w, float) >= min_weight
    m, P = np.asarray(m, float)[keep], np.asarray(P, float)[keep]
    if not len(m):
        return err, nees
    for i, y in enumerate(np.asarray(truths, float)):
        d = np.linalg.norm(m - y, axis=1)
        j = int(np.argmin(d))
        if d[j] <= within:
            err[i] = m[j] - y
            nees[i] = float(err[i] @ np.linalg.solve(P[j], err[i]))
    return err, nees


@dataclass
class PerVA:
    """The pooled errors of one true VA (rows: steps x seeds at which some vehicle had a path to it)."""

    position: np.ndarray
    err: list[np.ndarray] = field(default_factory=list)
    nees: list[float] = field(default_factory=list)

    def line(self, bs: np.ndarray, nn: float) -> str:
        e, n = np.array(self.err).reshape(-1, 3), np.array(self.nees, float)
        found = np.isfinite(e[:, 0])
        head = (f"true ({self.position[0]:8.2f}, {self.position[1]:8.2f}, {self.position[2]:6.2f})  "
                f"BS {np.linalg.norm(self.position - bs):6.1f} m  nearest VA {nn:7.2f} m  rows {len(e):4d}  "
                f"found {found.mean():4.0%}")
        if not found.any():
            return head
        return head + (f"  mean {np.round(e[found].mean(0), 2)}  rms {np.round(np.sqrt((e[found] ** 2).mean(0)), 2)}"
                       f"  NEES median {np.median(n[found]):.1f} mean {n[found].mean():.1f}")


def main(argv: list[str] | None = None) -> int:
    sys.path.insert(0, str(__import__("pathlib").Path(__file__).parent))
    from city_va import seeds_of  # noqa: PLC0415 (the same --seeds syntax)

    from mmslam.raytrace.cache import load_cache
    from mmslam.scenes.scenario import with_overrides
    from mmslam.slam.filter.precompile import ensure_compiled
    from mmslam.slam.filter.run import CooperativeRun
    from mmslam.slam.specs.landmarks import VA_SPEC

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("cache")
    ap.add_argument("--seeds", type=seeds_of, default=seeds_of("1000-1009"))
    ap.add_argument("--particles", type=int, default=300)
    ap.add_argument("--kmin", type=int, default=10)
    ap.add_argument("--variant", default="proposed")
    ap.add_argument("--within", type=float, default=3.0, help="largest distance (m) of a found Gaussian")
    ap.add_argument("--min-weight", type=float, default=0.5, help="lightest fused Gaussian considered")
    ap.add_argument("--set", action="append", default=[], help="section.key=value, as city_va.py")
    a = ap.parse_args(argv)

    c = load_cache(a.cache)
    scn = with_overrides(c.scenario, a.set)
    ensure_compiled([a.variant])
    paths = {k: np.asarray(v) for k, v in c.paths.items()}
    va = paths["type"] == VA_SPEC.code
    ids = paths["landmark_id"].astype(str)
    pos = np.stack([paths[f"lm_{x}"] for x in "xyz"], -1).astype(float)
    per: dict[str, PerVA] = {}
    for s in a.seeds:
        seed_err: list[np.ndarray] = []
        run = CooperativeRun(scn, c.states, c.paths, a.variant, a.particles, s, source=c.manifest.get("source"),
                             evaluate=False)
        if run.center is None:
            ap.error(f"--variant {a.variant}: no fused map (dead reckoning); use baseline, cm1 or proposed")
        for k in range(run.steps):
            run.step(k)
            if k < a.kmin:
                continue
            now = va & (paths["step"] == k)
            lid, first = np.unique(ids[now], return_index=True)
            truths = pos[now][first]
            g = run.center.maps.get(VA_SPEC.code)
            live = g.mask if g is not None else np.zeros(0, bool)
            err, nees = (nearest_errors(g.m[live, :3], g.w[live], g.P[live][:, :3, :3], truths, a.within, a.min_weight)
                         if g is not None else (np.full((len(truths), 3), np.nan), np.full(len(truths), np.nan)))
            seed_err.append(err)
            for i, name in enumerate(lid):
                rec = per.setdefault(name, PerVA(truths[i]))
                rec.err.append(err[i])
                rec.nees.append(nees[i])
        se = np.concatenate(seed_err) if seed_err else np.zeros((0, 3))
        sf = np.isfinite(se[:, 0])
        print(f"seed {s}: rows {len(se)}, found {sf.mean() if len(se) else float('nan'):.0%}, rms "
              f"{np.sqrt((se[sf] ** 2).sum(1).mean()) if sf.any() else float('nan'):.3f} m", flush=True)
    bs = np.asarray(scn.bs_array, float)
    allpos = np.unique(pos[va], axis=0)  # every true VA of the cache, seen at k >= kmin or not
    print(f"== {scn.name}: {a.variant}, P = {a.particles}, k >= {a.kmin}, seeds {a.seeds[0]}..{a.seeds[-1]} "
          f"({len(a.seeds)}), found = nearest fused Gaussian of weight >= {a.min_weight} within {a.within} m")
    for name, r in sorted(per.items(), key=lambda kv: tuple(kv[1].position)):
        others = np.linalg.norm(allpos - r.position, axis=1)
        nn = float(others[others > 1e-9].min()) if (others > 1e-9).any() else float("inf")
        print(f"  {name[:48]:48s} " + r.line(bs, nn))
    e = np.concatenate([np.array(r.err).reshape(-1, 3) for r in per.values()]) if per else np.zeros((0, 3))
    n = np.concatenate([np.array(r.nees, float) for r in per.values()]) if per else np.zeros(0)
    f = np.isfinite(e[:, 0]) if len(e) else np.zeros(0, bool)
    if f.any():
        print(f"  all VAs: rows {len(e)}, found {f.mean():.0%}, mean {np.round(e[f].mean(0), 3)}, rms per axis "
              f"{np.round(np.sqrt((e[f] ** 2).mean(0)), 3)}, rms {np.sqrt((e[f] ** 2).sum(1).mean()):.3f} m, "
              f"median {np.median(np.linalg.norm(e[f], axis=1)):.3f} m, NEES median {np.median(n[f]):.2f} "
              f"mean {n[f].mean():.2f}")
    else:
        print(f"  all VAs: rows {len(e)}, none found")
    return 0


if __name__ == "__main__":
    from script_entry import run

    run(main, "va_map_error.py")
