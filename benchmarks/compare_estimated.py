"""Estimated vs link measurements in one ablation (issue 24 acceptance): paired comparison over seeds.

Reads an ablation run with ``--grid sensor.model=link,estimated`` and prints, per arm of ``--variant``:
mean over seeds of the per-run fused-map GOSPA per type (mean over steps >= fusion start), the fused
VS map's PHD mass and estimate count at the last step, the vehicles' position RMSE; then the paired
difference estimated - link of the fused VA GOSPA with its 95 % CI (Student t over seeds); and the
estimator's evaluation counts per vehicle-step (the columns the runs store: estimates, detected, merged, false,
missed, suppressed).

    .venv/bin/mmslam ablate paper --source sionna --variants proposed --grid sensor.model=link,estimated \\
        --mc 10 --out out/abl_paper
    .venv/bin/python benchmarks/compare_estimated.py out/abl_paper
"""
from __future__ import annotations

import argparse
import json

import numpy as np

from mmslam.pipelines.ablate import ci95, load_jobs


def per_run(r, fusion_start: int) -> dict:
    m = r.metrics
    mp, ty, st = (np.asarray(m["map"]).astype(str), np.asarray(m["type"]).astype(str), np.asarray(m["step"]))
    out = {}
    for t in ("VA", "SP", "VS"):
        sel = (mp == "fused") & (ty == t) & (st >= fusion_start)
        out[f"gospa_{t}"] = float(np.nanmean(np.asarray(m["gospa"], float)[sel]))
    last = (mp == "fused") & (ty == "VS") & (st == st.max())
    out["vs_card_last"] = float(np.asarray(m["card"], float)[last][0])
    out["vs_n_est_last"] = float(np.asarray(m["n_est"], float)[last][0])
    vt = r.vehicles
    e = np.asarray(vt["pos_err"], float)[np.asarray(vt["step"]) >= fusion_start]
    out["pos_rmse"] = float(np.sqrt(np.mean(e * e)))
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("out_dir")
    ap.add_argument("--variant", default="proposed")
    a = ap.parse_args()
    jobs = load_jobs(a.out_dir, variants=[a.variant])
    arms: dict[str, dict[int, dict]] = {}
    counts, columns = [], None
    for job, r in jobs.items():
        arm = dict(kv.split("=", 1) for kv in job.arm).get("sensor.model", "?")
        fs = int(r.meta.get("fusion_start", 0))
        arms.setdefault(arm, {})[job.seed] = per_run(r, fs)
        if "estimator_counts" in r.meta:  # (steps, vehicles, columns), the columns named in the run's meta
            ec = r.meta["estimator_counts"]
            columns = list(ec["columns"])
            counts.append(np.asarray(ec["per_step_vehicle"], float).reshape(-1, len(columns)))
    res: dict = {}
    for arm, runs in sorted(arms.items()):
        keys = next(iter(runs.values())).keys()
        res[arm] = {k: ci95(np.array([runs[s][k] for s in runs])) for k in keys}
        print(f"{a.variant}[sensor.model={arm}] ({len(runs)} runs): " + ", ".join(
            f"{k} {m:.2f} +- {h:.2f}" for k, (m, h) in res[arm].items()))
        res[arm]["runs"] = len(runs)
    if {"link", "estimated"} <= set(arms):
        common = sorted(set(arms["link"]) & set(arms["estimated"]))
        for k in ("gospa_VA", "gospa_VS", "pos_rmse"):
            d = np.array([arms["estimated"][s][k] - arms["link"][s][k] for s in common])
            m, h = ci95(d)
            res[f"diff_{k}"] = (m, h, len(common))
            print(f"paired estimated - link, fused {k}: {m:+.2f} +- {h:.2f} (95 % CI, {len(common)} seeds)")
    if counts:
        c = np.concatenate(counts)
        res["estimator_counts_mean_per_vehicle_step"] = dict(zip(columns, c.mean(0).round(2).tolist()))
        print("estimator counts per vehicle-step (mean):", res["estimator_counts_mean_per_vehicle_step"])
    print(json.dumps(res, default=float))


if __name__ == "__main__":
    main()
