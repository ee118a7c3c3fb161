"""Why truths are missing from the fused VA map: each truth VA of each step classified by the fused map's Gaussians
near it (development diagnostic; docs/city-slam.md, "What the maps past 0.6 miss").

    python benchmarks/va_misses.py CACHE [--seeds 5000-5004] [--kmin 10] [--set section.key=value ...]

For each seed, the ``proposed`` filter (P = 300) runs step by step on the cache; at every step ``k >= kmin`` each VA
of the fused map's truth (first seen at or before ``k`` by some vehicle inside its FOV,
:func:`mmslam.slam.eval.evaluation.first_seen`) is put in one class by the live Gaussians of the BS's fused VA map
(:func:`classify`), and in one of two groups by the number of distinct steps ``<= k`` some vehicle could detect it:
``seen1`` (one step: no two-detection filter can have it, docs/city-slam.md "The two-detection floor") or
``seen2+``. Printed: the mean number of truths per step in each group and class, and of the extracted estimates in each
class of :data:`EST_CLASSES`. Positions in the global frame, m.
"""
from __future__ import annotations

import argparse
import sys
from collections import Counter

import numpy as np

CLASSES: tuple[str, ...] = ("found", "low", "shared", "off", "none")
"""``found``: a Gaussian within ``near`` with weight >= the threshold; ``low``: Gaussians within ``near``, all below
it; ``shared``: the nearest Gaussian within ``far`` is within ``near`` of another truth (one estimate for two
truths); ``off``: the nearest Gaussian within ``far`` is no truth's (a mislocated estimate); ``none``: no Gaussian
within ``far``."""


def classify(truth: np.ndarray, est_m: np.ndarray, est_w: np.ndarray, threshold: float, near: float = 1.5,
             far: float = 5.0) -> list[str]:
    """The class (:data:`CLASSES`) of each truth.

    Args:
        truth: ``(n, 3)`` truth positions (m); est_m: ``(q, 3)`` Gaussian means (m); est_w: ``(q,)`` their weights.
        threshold: the estimate threshold of the map's type (``filter.types.VA.threshold``).
        near, far: the radii (m) of a match and of a neighbour.

    Returns:
        ``n`` class names.
    """
    truth = np.asarray(truth, float).reshape(-1, 3)
    est_m, est_w = np.asarray(est_m, float).reshape(-1, 3), np.asarray(est_w, float).reshape(-1)
    n = truth.shape[0]
    if n == 0 or est_m.shape[0] == 0:
        return ["none"] * n
    d = np.linalg.norm(truth[:, None, :] - est_m[None, :, :], axis=-1)  # (n, q)
    close = d < near
    has_close = close.any(axis=1)
    found = has_close & (np.where(close, est_w[None, :], -np.inf).max(axis=1) >= threshold)
    nearest = est_m[np.argmin(d, axis=1)]  # (n, 3): each truth's nearest Gaussian
    to_truths = np.linalg.norm(nearest[:, None, :] - truth[None, :, :], axis=-1)  # (n, n)
    to_truths[np.arange(n), np.arange(n)] = np.inf  # another truth's, not its own
    neighbour = ~has_close & (d.min(axis=1) < far)
    shared = neighbour & (to_truths.min(axis=1) < near)
    cls = np.select([found, has_close, shared, neighbour], ["found", "low", "shared", "off"], "none")
    return cls.tolist()


EST_CLASSES: tuple[str, ...] = ("true", "near", "later", "far")
"""An extracted estimate's class, the first that applies: ``true``, within ``near`` of a truth of the step; ``near``,
within ``far`` of one; ``later``, within ``near`` of a VA first seen after the step (not yet in the truth: a false
estimate now); ``far``, none of these (clutter, or a VA no car could detect)."""


def estimate_classes(est: np.ndarray, truth: np.ndarray, later: np.ndarray, near: float = 1.5, far: float = 5.0
                     ) -> list[str]:
    """The class (:data:`EST_CLASSES`) of each estimate ``est (q, 3)`` (m) against the step's truths ``(n, 3)`` and
    the VAs first seen later ``(n', 3)``."""
    est = np.asarray(est, float).reshape(-1, 3)

    def dmin(pts: np.ndarray) -> np.ndarray:
        pts = np.asarray(pts, float).reshape(-1, 3)
        if pts.shape[0] == 0:
            return np.full(est.shape[0], np.inf)
        return np.linalg.norm(est[:, None, :] - pts[None, :, :], axis=-1).min(axis=1)

    d_now, d_later = dmin(truth), dmin(later)
    cls = np.select([d_now < near, d_now < far, d_later < near], ["true", "near", "later"], "far")
    return cls.tolist()


def parse_seeds(text: str) -> list[int]:
    """``"5000-5004"`` or ``"1,2,7"`` (ranges and single seeds, comma separated) -> seeds; argparse's one-line error
    (exit 2) for anything else."""
    out: list[int] = []
    try:
        for part in text.split(","):
            a, _, b = part.partition("-")
            out += list(range(int(a), int(b) + 1)) if b else [int(a)]
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: expected seeds such as 5000-5004 or 1,2,7") from None
    if not out:
        raise argparse.ArgumentTypeError(f"{text!r}: no seed in it")
    return out


def run(cache: str, seeds: list[int], kmin: int, overrides: list[str]) -> Counter:
    """``(group, class) -> truths summed over the steps >= kmin of every seed``, and ``"steps"`` -> their number."""
    from mmslam.raytrace.cache import load_cache
    from mmslam.scenes.scenario import with_overrides
    from mmslam.slam.eval.evaluation import estimates_of, first_seen, merge_seen, sightings
    from mmslam.slam.filter import CooperativeRun
    from mmslam.slam.specs.landmarks import VA_SPEC

    c = load_cache(cache)
    scn = with_overrides(c.scenario, overrides)
    steps, n_veh = c.states.shape[:2]
    pos, res, va = c.states[:, :, 0:3], float(scn.evaluation.va_resolution), VA_SPEC.code
    seen = merge_seen(first_seen(c.paths, n_veh, steps, pos, scn.sensor, res)[va])
    seen_at = sightings(c.paths, steps, pos, scn.sensor, res)[va]
    keys = list(seen)
    kpos = np.array([seen[k][1] for k in keys], float).reshape(-1, 3)
    kfirst = np.array([seen[k][0] for k in keys], int)
    thr = float(scn.filter.type_params("VA").threshold)
    tot: Counter = Counter()
    for s in seeds:
        cr = CooperativeRun(scn, c.states, c.paths, "proposed", 300, s, steps, source=c.manifest.get("source"))
        for k in range(steps):
            cr.step(k)
            if k < kmin or cr.center is None:
                continue
            g = cr.center.maps[va]
            live = np.asarray(g.mask, bool)
            now = np.nonzero(kfirst <= k)[0]
            for j, cls in zip(now, classify(kpos[now], g.m[live][:, :3], g.w[live], thr)):
                n = sum(1 for t in seen_at.get(str(keys[j]), ()) if t <= k)
                tot[("seen1" if n < 2 else "seen2+", cls)] += 1
            est, _ = estimates_of(g, thr, scn.filter.extraction)  # what GOSPA scores (w > threshold)
            for cls in estimate_classes(est, kpos[now], kpos[kfirst > k]):
                tot[("estimates", cls)] += 1
            tot["steps"] += 1
    return tot


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("cache")
    ap.add_argument("--seeds", type=parse_seeds, default="5000-5004")
    ap.add_argument("--kmin", type=int, default=10)
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    a = ap.parse_args(argv)
    from mmslam.errors import MmslamError

    try:
        tot = run(a.cache, a.seeds, a.kmin, a.set)
    except MmslamError as e:  # a missing or unreadable cache, a bad --set: one line, nothing was computed
        print(f"va_misses: {e}", file=sys.stderr)
        return 2
    n = max(tot.pop("steps", 0), 1)
    print(f"truth VAs per step, fused map, k >= {a.kmin}, {len(a.seeds)} seeds:")
    for grp in ("seen1", "seen2+"):
        print(f"  {grp:7s} " + "  ".join(f"{c} {tot[(grp, c)] / n:.2f}" for c in CLASSES))
    print("estimates per step (those the map's GOSPA scores):")
    print("          " + "  ".join(f"{c} {tot[('estimates', c)] / n:.2f}" for c in EST_CLASSES))
    return 0


if __name__ == "__main__":
    sys.exit(main())
