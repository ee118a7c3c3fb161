"""Second-order reflections (issue 24): depth 1 vs depth 2 traces, `estimated` vs `link` measurements.

Reads two ablations of the same scenario, one on a ``--max-depth 1`` and one on a ``--max-depth 2`` Sionna
trace, each with ``--grid sensor.model=estimated,link``, and prints per (depth, model) the mean over seeds
(95 % CI, Student t) of the fused map's GOSPA per type (steps >= fusion start) and the vehicles' position
RMSE; the fused VA GOSPA also re-scored against the order-1 VAs only (the truth without the order-2 image
sources: :func:`rescore_va`); the paired differences estimated - link (per depth) and depth 2 - depth 1 (per
model, same seeds: both traces share the vehicles' truth); and per vehicle-step the order-1 / order-2 VA
rows of each trace and the estimates labelled with an order-2 VA (from the estimates cache).

    mmslam trace canyon --source sionna --max-depth 2 --out /tmp/depth2/cache
    mmslam ablate canyon --source sionna --max-depth 1 --variants proposed --grid sensor.model=estimated,link --mc 10 --out D1
    mmslam ablate canyon --source sionna --max-depth 2 --variants proposed --grid sensor.model=estimated,link --mc 10 --out D2
    python benchmarks/depth2_canyon.py D1 D2
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from mmslam.pipelines.ablate import ci95, load_jobs
from mmslam.raytrace.cache import load_cache
from mmslam.scenes.scenario import with_overrides
from mmslam.slam.eval.evaluation import MapScorer
from mmslam.slam.eval.gospa import gospa
from mmslam.model import VA

from compare_estimated import per_run


def order2(paths: dict) -> np.ndarray:
    """Rows of ``paths`` that are VAs of order 2 (``bounces == 2``)."""
    return (np.asarray(paths["type"]) == VA) & (np.asarray(paths["bounces"]) == 2)


MAPPED_M = 2.0
"""m: a true VA counts as mapped at the last step if a fused VA estimate is within this distance."""


def _scorer(r, cache, rows: str) -> tuple[MapScorer, int]:
    """A scorer of the run's truth from the cache's paths: ``rows`` "all", "order1" (order-2 VA rows dropped)
    or "order2" (the order-2 VA rows only); and the run's step count."""
    scn = with_overrides(cache.scenario, list(r.meta.get("overrides", [])))
    steps = int(np.max(r.metrics["step"])) + 1
    paths = {k: np.asarray(v) for k, v in cache.paths.items()}
    keep = np.asarray(paths["step"]) < steps
    if rows == "order1":
        keep &= ~order2(paths)
    elif rows == "order2":
        keep &= order2(paths)
    return MapScorer(scn, {k: v[keep] for k, v in paths.items()}, cache.states[:steps], list(scn.vehicle_names)), steps


def _fused_va(r) -> tuple[np.ndarray, np.ndarray]:
    """The run's fused VA estimates: positions ``(n, 3)`` and their steps ``(n,)``."""
    L = r.landmarks
    sel = (np.asarray(L["map"]).astype(str) == "fused") & (np.asarray(L["type"]).astype(str) == "VA")
    return np.stack([np.asarray(L[c], float) for c in "xyz"], -1)[sel], np.asarray(L["step"])[sel]


def rescore_va(r, cache, fusion_start: int, drop_order2: bool) -> float:
    """The run's fused VA GOSPA (mean over steps >= ``fusion_start``) against the truth built from the cache's
    paths, without the order-2 VA rows if ``drop_order2`` (the stored estimates re-scored)."""
    sc, steps = _scorer(r, cache, "order1" if drop_order2 else "all")
    xyz, lst = _fused_va(r)
    ev = sc.scn.evaluation
    d = [gospa(sc.fused_truth(k)[VA], xyz[lst == k], ev.gospa_c, ev.gospa_p, ev.gospa_alpha).d
         for k in range(fusion_start, steps)]
    return float(np.mean(d))


def mapped_at_last_step(r, cache, rows: str) -> tuple[float, float]:
    """(true VAs of ``rows`` ("order1" / "order2") seen by the last step, those with a fused VA estimate
    within :data:`MAPPED_M`)."""
    sc, steps = _scorer(r, cache, rows)
    xyz, lst = _fused_va(r)
    Y = sc.fused_truth(steps - 1)[VA]
    X = xyz[lst == steps - 1]
    if not len(Y) or not len(X):
        return float(len(Y)), 0.0
    d = np.linalg.norm(Y[:, None, :] - X[None, :, :], axis=-1)
    return float(len(Y)), float(np.sum(d.min(axis=1) <= MAPPED_M))


def collect(abl: str, variant: str) -> tuple[dict, dict]:
    """``{model: {seed: metrics}}`` of one ablation and the counts of its trace / estimates."""
    jobs = load_jobs(abl, variants=[variant])
    cache = load_cache(next(iter(jobs.values())).meta["cache_path"])
    arms: dict[str, dict[int, dict]] = {}
    for job, r in jobs.items():
        model = dict(kv.split("=", 1) for kv in job.arm).get("sensor.model", "?")
        fs = int(r.meta.get("fusion_start", 0))
        m = per_run(r, fs)
        m["gospa_VA_order1_truth"] = rescore_va(r, cache, fs, drop_order2=True)
        for rows in ("order1", "order2"):
            m[f"true_VA_{rows}_last"], m[f"mapped_VA_{rows}_last"] = mapped_at_last_step(r, cache, rows)
        mt = r.metrics
        sel = ((np.asarray(mt["map"]).astype(str) == "fused") & (np.asarray(mt["type"]).astype(str) == "VA")
               & (np.asarray(mt["step"]) >= fs))
        m["n_est_VA"] = float(np.mean(np.asarray(mt["n_est"], float)[sel]))
        check = rescore_va(r, cache, fs, drop_order2=False)
        assert abs(check - m["gospa_VA"]) < 1e-9, (check, m["gospa_VA"])  # the re-scoring reproduces the run's
        arms.setdefault(model, {})[job.seed] = m
    p = cache.paths
    n_vs = cache.states.shape[0] * cache.states.shape[1]
    va = np.asarray(p["type"]) == VA
    counts = {"VA order-1 rows per vehicle-step": float(np.sum(va & ~order2(p)) / n_vs),
              "VA order-2 rows per vehicle-step": float(np.sum(order2(p)) / n_vs)}
    est = sorted(Path(cache.path, "estimates").glob(f"*/seed-*-steps-{cache.states.shape[0]}.npz"))
    if est:
        o2, o1, tot, cnt = [], [], [], []
        for f in est:
            d = np.load(f, allow_pickle=True)
            ot, oid = d["origin_type"], np.asarray(d["origin_id"]).astype(str)
            isva = ot == VA
            two = isva & (np.char.find(oid, "|") >= 0)
            o2.append(two.sum()); o1.append((isva & ~two).sum()); tot.append(len(ot))
            n_vs_est = d["counts"].shape[0] * d["counts"].shape[1]
            cnt.append(np.asarray(d["counts"], float).reshape(-1, 5).mean(0))
        counts["estimates per vehicle-step"] = float(np.mean(tot) / n_vs_est)
        counts["estimates labelled VA order 1 per vehicle-step"] = float(np.mean(o1) / n_vs_est)
        counts["estimates labelled VA order 2 per vehicle-step"] = float(np.mean(o2) / n_vs_est)
        for name, v in zip(("estimates", "detected", "merged", "false", "missed"), np.mean(cnt, axis=0)):
            counts[f"estimator counts: {name}"] = float(v)  # per vehicle-step (estimated_sensor COUNT_COLUMNS)
    return arms, counts


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("depth1")
    ap.add_argument("depth2")
    ap.add_argument("--variant", default="proposed")
    a = ap.parse_args()
    runs, res = {}, {}
    for depth, abl in ((1, a.depth1), (2, a.depth2)):
        arms, counts = collect(abl, a.variant)
        res[f"depth{depth} counts"] = counts
        print(f"depth {depth}: " + ", ".join(f"{k} {v:.2f}" for k, v in counts.items()))
        for model, by_seed in sorted(arms.items()):
            runs[(depth, model)] = by_seed
            keys = next(iter(by_seed.values())).keys()
            res[f"depth{depth} {model}"] = {k: ci95(np.array([by_seed[s][k] for s in sorted(by_seed)])) for k in keys}
            print(f"depth {depth} {model} ({len(by_seed)} runs): " + ", ".join(
                f"{k} {m:.2f} +- {h:.2f}" for k, (m, h) in res[f"depth{depth} {model}"].items()))
    pairs = [((d, "estimated"), (d, "link")) for d in (1, 2)] + [((2, m), (1, m)) for m in ("estimated", "link")]
    for x, y in pairs:
        if x not in runs or y not in runs:
            continue
        common = sorted(set(runs[x]) & set(runs[y]))
        for k in ("gospa_VA", "gospa_VA_order1_truth", "gospa_VS", "pos_rmse"):
            m, h = ci95(np.array([runs[x][s][k] - runs[y][s][k] for s in common]))
            res[f"{x} - {y} {k}"] = (m, h, len(common))
            print(f"paired depth{x[0]} {x[1]} - depth{y[0]} {y[1]}, {k}: {m:+.2f} +- {h:.2f} (95 % CI, {len(common)} seeds)")
    print(json.dumps({k: v for k, v in res.items()}, default=float))


if __name__ == "__main__":
    main()
