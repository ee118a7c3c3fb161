"""Aggregation of finished jobs: per-step mean / std / RMS over seeds, the headline table with 95% CIs
and paired differences to ``baseline``; ``summary.parquet`` / ``summary.json``."""
from __future__ import annotations

import json
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from mmslam.errors import CacheError
from mmslam.slam.specs.variants import COMPARED_WITH, variant_names
from mmslam.pipelines.ablate.executors import _one_line
from mmslam.pipelines.ablate.options import (ALL_VEHICLES, JOBS_DIR, Job, METRIC_QUANTITIES, STATE_QUANTITIES,
                                             SUMMARY_JSON, SUMMARY_PARQUET, TYPES, VARIANTS, arm_label,
                                             is_finished, job_dir, parse_label)
from mmslam.pipelines.ablate.store import _write_json, read_ablation, remove_stale_temps, temp_path
from mmslam.pipelines.ablate.sensor_models import measurement_rows, sensor_model, sensor_pairs
from mmslam.pipelines.ablate.stats import ci95  # noqa: F401  (re-exported)


@dataclass
class Summary:
    """Aggregated ablation results.

    ``table`` (long form, one row per variant, step, map, type and quantity):
        variant, map (vehicle name, ``"fused"``, or ``"all"`` for state rows pooled over
        vehicles), type (``VA``/``SP``/``VS`` for map metrics, ``"state"`` for vehicle-state
        errors), quantity (:data:`METRIC_QUANTITIES` or :data:`STATE_QUANTITIES`), step,
        mean, std (population std, ddof 0, over the pooled samples), rms (root mean square),
        n (samples pooled: seeds, times vehicles for ``map == "all"``).
    ``headline``: one row per variant (or grid arm, ``variant[key=value]``) and map (each
        vehicle, then ``fused``): mean GOSPA per type over seeds and steps ``>= fusion_start``,
        position RMSE over the same steps (the vehicle's, or all vehicles' for ``fused``), the median
        position NEES ``pos_nees`` over the same vehicle-steps (:func:`_median_nees`; 1.39 when consistent), mean
        job wall time and the seed count; for each of :data:`SCORED` the 95% CI half-width
        ``_ci`` of the mean over runs (per-run scores: mean GOSPA, RMSE), the paired difference
        ``_diff`` to ``reference`` (baseline on the same seeds) with its CI ``_diff_ci`` and
        ``_sig`` (True when that CI excludes 0); ``card_<type>``: mean PHD mass (estimated
        number of landmarks) over the same steps and runs. Each score is the mean over runs of the
        per-run score, the statistic its CI is of (the RMSE: mean of the per-run RMSEs; a pooled
        RMSE over all runs, printed before issue 23 with this CI, is ``pos_rmse_pooled``).
    ``config``: the ablation settings (:data:`ABLATION_FILE`) plus ``fusion_start``.
    """

    table: dict[str, np.ndarray]
    headline: list[dict[str, Any]]
    config: dict[str, Any] = field(default_factory=dict)
    paired: dict[str, list] = field(default_factory=dict)
    """Per-step paired differences to the reference arm (:func:`paired_steps`): columns variant,
    reference, quantity (``gospa_VA``, ``gospa_SP``, ``gospa_VS`` of the fused map; ``pos_err``, the
    position error averaged over the vehicles), step, diff (mean over the common seeds of the per-run
    difference), ci (95% Student-t half-width), n (seeds), sig (the CI excludes 0)."""
    sensor: dict[str, list] = field(default_factory=dict)
    """``measurements``: :func:`~mmslam.pipelines.ablate.sensor_models.measurement_rows` (what each label's
    filter was given, per vehicle-step); ``pairs``: :func:`~mmslam.pipelines.ablate.sensor_models.sensor_pairs`."""

    def paired_series(self, variant: str, quantity: str) -> dict[str, np.ndarray]:
        """Per-step columns (step, diff, ci, n) of ``variant`` minus its reference for ``quantity``."""
        p = self.paired
        if not p:
            return {k: np.zeros(0) for k in ("step", "diff", "ci", "n")}
        m = (np.asarray(p["variant"], object) == variant) & (np.asarray(p["quantity"], object) == quantity)
        order = np.argsort(np.asarray(p["step"])[m], kind="stable")
        return {k: np.asarray(p[k], float)[m][order] for k in ("step", "diff", "ci", "n")}

    def series(self, variant: str, map: str, type: str, quantity: str) -> dict[str, np.ndarray]:
        """Per-step columns (step, mean, std, rms, n) of one (variant, map, type, quantity)."""
        t = self.table
        m = ((t["variant"] == variant) & (t["map"] == map) & (t["type"] == type)
             & (t["quantity"] == quantity))
        order = np.argsort(t["step"][m], kind="stable")
        return {k: np.asarray(t[k][m])[order] for k in ("step", "mean", "std", "rms", "n")}

    @property
    def variants(self) -> list[str]:
        """Variant / arm labels present, in :data:`VARIANTS` order (arms after their variant)."""
        present = list(dict.fromkeys(np.asarray(self.table["variant"]).tolist()))
        order = {v: i for i, v in enumerate(variant_names())}
        return sorted(present, key=lambda lab: (order.get(parse_label(lab)[0], 99), present.index(lab)))


def upload_steps(scenario: dict[str, Any], steps: int) -> list[int] | None:
    """The steps with an upload (any vehicle's ``fusion.start + i fusion.period``) when the scenario's
    ``evaluation.fused_steps`` is ``uploads`` (the fused map's headline GOSPA is their mean), else None."""
    from mmslam.scenes.scenario import scenario_from_resolved

    if not scenario:
        return None
    scn = scenario_from_resolved(scenario)
    if scn.evaluation.fused_steps != "uploads":
        return None
    fu = scn.fusion
    return sorted({k for st in fu.start for k in range(int(st), int(steps), int(fu.period))})


def _fusion_start(scenario: dict[str, Any]) -> int:
    try:
        return int(min(scenario["fusion"]["start"]))
    except (KeyError, TypeError, ValueError):
        return 0


def spec_arms(spec: dict[str, Any]) -> list[tuple[str, ...]]:
    """The grid arms recorded in ``ablation.json`` (one empty arm for an ablation without ``--grid``)."""
    return [tuple(a) for a in spec.get("arms", [[]])] or [()]


def nonfinite_values(result: Any) -> list[tuple[str, int, int]]:
    """``(table.column, count, first step)`` of every aggregated column of a job's result holding NaN or
    infinite values (:data:`METRIC_QUANTITIES` of ``metrics``, :data:`STATE_QUANTITIES` of ``vehicles``)."""
    bad = []
    for table, cols in (("metrics", METRIC_QUANTITIES), ("vehicles", STATE_QUANTITIES)):
        t = getattr(result, table)
        for c in cols:
            if c not in t:
                continue
            a = np.asarray(t[c], dtype=float)
            nf = ~np.isfinite(a)
            if nf.any():
                bad.append((f"{table}.{c}", int(nf.sum()), int(np.asarray(t["step"])[nf][0])))
    return bad


def check_result_finite(result: Any, what: str, fix: str, exit_code: int = 2) -> None:
    """One-line :class:`CacheError` naming ``what`` and ``fix`` if :func:`nonfinite_values` finds any.

    A mean over seeds must never drop a run silently: a non-finite value fails its job (the summary's
    ``runs`` would otherwise count a run whose value vanished from the mean and its CI).
    """
    bad = nonfinite_values(result)
    if bad:
        col, n, step = bad[0]
        more = f" (and {len(bad) - 1} more columns)" if len(bad) > 1 else ""
        raise CacheError(f"{what}: {n} non-finite value{'s' if n > 1 else ''} in {col}, first at step {step}{more}; "
                         f"{fix}", exit_code=exit_code)


def load_jobs(out_dir: str | Path, variants: Sequence[str] | None = None,
              seeds: Sequence[int] | None = None) -> dict[Job, Any]:
    """Finished jobs of the ablation in ``out_dir`` (default: its whole grid), loaded.

    Raises:
        CacheError: a stored job holds a non-finite value (:func:`check_result_finite`).
    """
    from mmslam.slam.filter.result import Result

    spec = read_ablation(out_dir)
    variants = list(variants or spec.get("variants", VARIANTS))
    seeds = list(seeds if seeds is not None else spec.get("seeds", range(int(spec.get("mc", 0)))))
    out = {}
    for v in variants:
        for a in spec_arms(spec):
            for s in seeds:
                j = Job(v, int(s), a)
                if is_finished(out_dir, j):
                    d = job_dir(out_dir, j)
                    out[j] = Result.load(d)
                    check_result_finite(out[j], str(d), f"results are never stored non-finite, so it was edited "
                                        f"or damaged: delete {d} and re-run the ablation to recompute it")
    return out


def _group_stats(keys: list[tuple], values: np.ndarray) -> dict[tuple, tuple[float, float, float, int]]:
    """Key -> (mean, std, rms, n) of the values (NaNs ignored)."""
    acc: dict[tuple, list[float]] = {}
    for k, v in zip(keys, values.tolist()):
        acc.setdefault(k, []).append(v)
    out = {}
    for k, vs in acc.items():
        a = np.asarray(vs, dtype=float)
        a = a[np.isfinite(a)]
        if a.size:
            out[k] = (float(a.mean()), float(a.std()), float(np.sqrt(np.mean(a * a))), int(a.size))
        else:
            out[k] = (math.nan, math.nan, math.nan, 0)
    return out


def aggregate(out_dir: str | Path) -> Summary:
    """Mean / std / RMS over seeds of every per-step metric; writes ``summary.parquet`` / ``.json``.

    Uses the finished jobs of the ablation's grid (a partial grid is aggregated over the seeds
    present; ``n`` and the headline ``runs`` say how many). See :class:`Summary` for the columns.
    """
    out = Path(out_dir)
    spec = read_ablation(out)
    remove_stale_temps(out, SUMMARY_FILES)
    jobs = load_jobs(out)
    if not jobs:
        raise CacheError(f"{out}: no finished jobs under {out / JOBS_DIR}; run the ablation first")
    fusion_start = _fusion_start(spec.get("scenario", {}))
    uploads = upload_steps(spec.get("scenario", {}), int(spec.get("steps") or 0))
    rows: dict[str, list] = {k: [] for k in ("variant", "map", "type", "quantity", "step", "mean", "std",
                                             "rms", "n")}
    headline: list[dict[str, Any]] = []
    labels = _labels_in_order(jobs, spec_arms(spec))
    per_run: dict[str, dict[int, dict[str, dict[str, float]]]] = {}
    for variant in labels:
        res = [jobs[j] for j in sorted(jobs) if j.label == variant]
        names = list(res[0].meta.get("vehicle_names") or spec.get("vehicle_names") or [])
        # ---- map metrics, grouped by (map, type, step)
        mkeys: list[tuple] = []
        mvals: dict[str, list[np.ndarray]] = {q: [] for q in METRIC_QUANTITIES}
        for r in res:
            m = r.metrics
            mkeys += list(zip(np.asarray(m["map"]).astype(str).tolist(), np.asarray(m["type"]).astype(str).tolist(),
                              np.asarray(m["step"]).astype(int).tolist()))
            for q in METRIC_QUANTITIES:
                mvals[q].append(np.asarray(m[q], dtype=float) if q in m  # results saved before a column existed
                                else np.full(len(m["step"]), math.nan))
        for q in METRIC_QUANTITIES:
            for (mp, ty, st), (mu, sd, rm, n) in sorted(_group_stats(mkeys, np.concatenate(mvals[q])).items()):
                for k, v in zip(rows, (variant, mp, ty, q, st, mu, sd, rm, n)):
                    rows[k].append(v)
        # ---- vehicle-state errors, per vehicle and pooled
        vkeys: list[tuple] = []
        akeys: list[tuple] = []
        vvals: dict[str, list[np.ndarray]] = {q: [] for q in STATE_QUANTITIES}
        for r in res:  # vehicle states: per vehicle and pooled (no map is involved)
            vt = r.vehicles
            idx = np.asarray(vt["vehicle"]).astype(int)
            st = np.asarray(vt["step"]).astype(int).tolist()
            vn = [names[i] if i < len(names) else f"vehicle{i}" for i in idx.tolist()]
            vkeys += list(zip(vn, st))
            akeys += [(ALL_VEHICLES, s) for s in st]
            for q in STATE_QUANTITIES:
                vvals[q].append(np.asarray(vt[q], dtype=float))
        for q in STATE_QUANTITIES:
            vals = np.concatenate(vvals[q])
            for keys in (vkeys, akeys):
                for (mp, st), (mu, sd, rm, n) in sorted(_group_stats(keys, vals).items()):
                    for k, v in zip(rows, (variant, mp, "state", q, st, mu, sd, rm, n)):
                        rows[k].append(v)
        per_run[variant] = {int(r.meta.get("seed", i)): _run_scores(r, names, fusion_start, uploads)
                            for i, r in enumerate(res)}
        headline += _headline_rows(variant, res, names, fusion_start, uploads)
    _add_intervals(headline, per_run)
    paired = paired_steps({lab: {int(r.meta.get("seed", i)): _run_series(r)
                                 for i, r in enumerate(jobs[j] for j in sorted(jobs) if j.label == lab)}
                           for lab in labels})
    table = {k: np.asarray(v, dtype=object if k in ("variant", "map", "type", "quantity") else None)
             for k, v in rows.items()}
    table["step"] = table["step"].astype(np.int32)
    table["n"] = table["n"].astype(np.int32)
    config = {**{k: v for k, v in spec.items() if k != "scenario"}, "fusion_start": fusion_start,
              "truth": spec.get("truth", "fixed"),
              "fused_headline_steps": "all from fusion_start" if uploads is None else uploads,
              "dt": spec.get("scenario", {}).get("dt"),
              "seeds_found": {v: sorted(j.seed for j in jobs if j.label == v) for v in labels}}
    models = {lab: sensor_model(lab, spec, [jobs[j].meta for j in jobs if j.label == lab]) for lab in labels}
    sensor = {"measurements": measurement_rows(jobs, labels, spec), "pairs": sensor_pairs(per_run, models)}
    summary = Summary(table, headline, config, paired, sensor)
    _write_summary(out, summary)
    return summary


def _labels_in_order(jobs: dict[Job, Any], arms: Sequence[tuple[str, ...]]) -> list[str]:
    """Job labels: variants in :data:`VARIANTS` order, each followed by its grid arms in ``arms`` order."""
    order = {v: i for i, v in enumerate(variant_names())}
    arm_pos = {tuple(a): i for i, a in enumerate(arms)}
    ranked = sorted(jobs, key=lambda j: (order.get(j.variant, 99), arm_pos.get(j.arm, len(arm_pos)), j.arm))
    return list(dict.fromkeys(j.label for j in ranked))


OTHERS_MAP = "fused_others"
"""The fused VS map without the vehicles' own uploads (:meth:`mmslam.slam.eval.evaluation.MapScorer.record_others`):
VS mapping of *other* vehicles, a headline row of its own where the runs have it."""


def _maps(names: list[str], res: Sequence[Any]) -> list[str]:
    """Headline maps: each vehicle, ``fused``, then :data:`OTHERS_MAP` where some run scored it."""
    has = any(np.any(np.asarray(r.metrics["map"]).astype(str) == OTHERS_MAP) for r in res)
    return list(names) + ["fused"] + ([OTHERS_MAP] if has else [])


def _run_scores(r: Any, names: list[str], fusion_start: int, uploads: Sequence[int] | None = None
                ) -> dict[str, dict[str, float]]:
    """One run's scalar scores per map: mean GOSPA and PHD mass per type, position RMSE (steps >= fusion_start;
    the fused maps' GOSPA only over ``uploads`` when given, :func:`upload_steps`)."""
    m = r.metrics
    mp_col = np.asarray(m["map"]).astype(str)
    ty_col = np.asarray(m["type"]).astype(str)
    late = _late(m, fusion_start, mp_col, uploads)
    out: dict[str, dict[str, float]] = {}
    for mp in _maps(names, [r]):
        row: dict[str, float] = {}
        for ty in TYPES:
            sel = (mp_col == mp) & (ty_col == ty) & late
            g = np.asarray(m["gospa"], float)[sel]
            row[f"gospa_{ty}"] = float(g.mean()) if g.size else math.nan
            c = np.asarray(m["card"], float)[sel] if "card" in m else np.zeros(0)
            row[f"card_{ty}"] = float(c.mean()) if c.size else math.nan
        if mp == OTHERS_MAP:  # a VS score only: no vehicle state behind it
            row["pos_rmse"] = math.nan
            out[mp] = row
            continue
        e = _vehicle_values([r], names, mp, fusion_start, "pos_err")
        row["pos_rmse"] = float(np.sqrt(np.mean(e * e))) if e.size else math.nan
        out[mp] = row
    return out


PAIRED_QUANTITIES: tuple[str, ...] = tuple(f"gospa_{t}" for t in TYPES) + ("pos_err",)
"""Per-step quantities of :func:`paired_steps`: the fused map's GOSPA per type, the position error."""


def _run_series(r: Any) -> dict[str, dict[int, float]]:
    """One run's per-step values of :data:`PAIRED_QUANTITIES`: step -> fused GOSPA per type, and the
    position error (m) averaged over the vehicles."""
    m, vt = r.metrics, r.vehicles
    out: dict[str, dict[int, float]] = {}
    fused = np.asarray(m["map"]).astype(str) == "fused"
    ty_col, st = np.asarray(m["type"]).astype(str), np.asarray(m["step"]).astype(int)
    g = np.asarray(m["gospa"], float)
    for ty in TYPES:
        sel = fused & (ty_col == ty)
        out[f"gospa_{ty}"] = dict(zip(st[sel].tolist(), g[sel].tolist()))
    vs, e = np.asarray(vt["step"]).astype(int), np.asarray(vt["pos_err"], float)
    out["pos_err"] = {int(k): float(e[vs == k].mean()) for k in np.unique(vs)}
    return out


def paired_steps(series: dict[str, dict[int, dict[str, dict[int, float]]]]) -> dict[str, list]:
    """Per step, the paired difference of each label to its reference (:func:`_reference`) over the seeds
    both ran: mean and 95% Student-t half-width of ``value(label, seed, step) - value(ref, seed, step)``.

    ``series``: label -> seed -> quantity -> step -> value (:func:`_run_series`). Returns the long table
    of :attr:`Summary.paired`.
    """
    cols: dict[str, list] = {k: [] for k in ("variant", "reference", "quantity", "step", "diff", "ci", "n", "sig")}
    labels = list(series)
    for lab in labels:
        ref = _reference(lab, labels)
        if ref is None:
            continue
        seeds = sorted(set(series[lab]) & set(series[ref]))
        for q in PAIRED_QUANTITIES:
            steps = sorted({k for s in seeds for k in series[lab][s].get(q, {})})
            for k in steps:
                d = np.array([series[lab][s].get(q, {}).get(k, math.nan) - series[ref][s].get(q, {}).get(k, math.nan)
                              for s in seeds])
                mean, half = ci95(d)
                for c, v in zip(cols, (lab, ref, q, k, mean, half, int(np.isfinite(d).sum()),
                                       bool(math.isfinite(half) and abs(mean) > half) if math.isfinite(mean) else None)):
                    cols[c].append(v)
    return cols


SCORED: tuple[str, ...] = tuple(f"gospa_{t}" for t in TYPES) + ("pos_rmse",)
"""Headline scores that get a 95% CI over runs and a paired difference to ``baseline``."""


def _reference(label: str, labels: Sequence[str]) -> str | None:
    """The arm a label is compared with: :data:`~mmslam.slam.specs.variants.COMPARED_WITH` (``baseline``) with the
    same grid settings, else plain ``baseline``."""
    variant, arm = parse_label(label)
    if variant == COMPARED_WITH:
        return None
    for cand in (arm_label(COMPARED_WITH, arm), COMPARED_WITH):
        if cand in labels:
            return cand
    return None


def _add_intervals(headline: list[dict[str, Any]], per_run: dict[str, dict[int, dict[str, dict[str, float]]]]) -> None:
    """Add ``<score>_ci`` (95% CI half-width over runs), ``<score>_diff`` / ``_diff_ci`` / ``_sig`` (paired
    difference to the reference arm over the seeds both ran; ``_sig`` says whether the CI excludes 0)
    and ``card_<type>`` (mean PHD mass) to every headline row."""
    labels = list(per_run)
    for row in headline:
        label, mp = row["variant"], row["map"]
        runs = per_run[label]
        ref = _reference(label, labels)
        row["reference"] = ref
        for ty in TYPES:
            row[f"card_{ty}"] = ci95(np.array([runs[s][mp][f"card_{ty}"] for s in runs]))[0]
        row["pos_rmse_pooled"] = row["pos_rmse"]
        for q in SCORED:
            row[q], row[q + "_ci"] = ci95(np.array([runs[s][mp][q] for s in runs]))
            row[q + "_diff"] = row[q + "_diff_ci"] = math.nan
            row[q + "_sig"] = None
            if ref is None:
                continue
            common = [s for s in sorted(set(runs) & set(per_run[ref])) if mp in per_run[ref][s]]
            d = np.array([runs[s][mp][q] - per_run[ref][s][mp][q] for s in common])
            mean, half = ci95(d)
            row[q + "_diff"], row[q + "_diff_ci"] = mean, half
            row[q + "_sig"] = bool(math.isfinite(half) and abs(mean) > half) if math.isfinite(mean) else None


def _late(m: dict[str, np.ndarray], fusion_start: int, mp_col: np.ndarray, uploads: Sequence[int] | None) -> np.ndarray:
    """Metric rows scored in the headline: steps >= fusion_start; the fused maps' (``fused``,
    :data:`OTHERS_MAP`) only at ``uploads`` if given."""
    st = np.asarray(m["step"])
    late = st >= fusion_start
    if uploads is not None:
        late &= ~np.isin(mp_col, ("fused", OTHERS_MAP)) | np.isin(st, np.asarray(list(uploads), int))
    return late


def _headline_rows(variant: str, res: list[Any], names: list[str], fusion_start: int,
                   uploads: Sequence[int] | None = None) -> list[dict[str, Any]]:
    """Mean GOSPA per (map, type) and position RMSE over steps >= fusion_start, over all seeds (the fused
    maps' GOSPA only over ``uploads`` when given)."""
    maps = _maps(names, res)
    wall = [float(r.meta.get("wall_time_s", math.nan)) for r in res]
    rows = []
    for mp in maps:
        row: dict[str, Any] = {"variant": variant, "map": mp}
        for ty in TYPES:
            vals = []
            for r in res:
                m = r.metrics
                mpc = np.asarray(m["map"]).astype(str)
                sel = (mpc == mp) & (np.asarray(m["type"]).astype(str) == ty) & _late(m, fusion_start, mpc, uploads)
                vals.append(np.asarray(m["gospa"], dtype=float)[sel])
            a = np.concatenate(vals) if vals else np.zeros(0)
            a = a[np.isfinite(a)]
            row[f"gospa_{ty}"] = float(a.mean()) if a.size else math.nan
        if mp == OTHERS_MAP:  # a VS score only: no vehicle state behind it
            row["pos_rmse"] = row["pos_nees"] = math.nan
        else:
            e = _vehicle_values(res, names, mp, fusion_start, "pos_err")
            row["pos_rmse"] = float(np.sqrt(np.mean(e * e))) if e.size else math.nan
            row["pos_nees"] = _median_nees(res, names, mp, fusion_start)
        row["wall_time_s"] = float(np.nanmean(wall)) if wall and np.isfinite(wall).any() else math.nan
        row["runs"] = len(res)
        rows.append(row)
    return rows


NEES_CONSISTENT: float = 2.0 * math.log(2.0)
"""The median of a consistent 2-D position NEES (chi-square, 2 degrees of freedom): ``2 ln 2 = 1.386``."""


def _vehicle_values(res: Sequence[Any], names: list[str], mp: str, fusion_start: int, column: str) -> np.ndarray:
    """The finite values of one column of the vehicles tables of ``res`` at the vehicle-steps ``>= fusion_start``:
    vehicle ``mp``'s, or every vehicle's for ``fused``; ``(n,)``."""
    vals = []
    for r in res:
        vt = r.vehicles
        sel = np.asarray(vt["step"]) >= fusion_start
        if mp != "fused":
            sel &= np.asarray(vt["vehicle"]).astype(int) == names.index(mp)
        vals.append(np.asarray(vt[column], dtype=float)[sel])
    a = np.concatenate(vals) if vals else np.zeros(0)
    return a[np.isfinite(a)]


def _median_nees(res: Sequence[Any], names: list[str], mp: str, fusion_start: int) -> float:
    """The median of the horizontal position NEES (``pos_nees`` of the vehicles table,
    :func:`~mmslam.slam.filter.rbpf.position_nees`) over the vehicle-steps ``>= fusion_start`` of every run (one
    vehicle's, or all for ``fused``), pooled: :data:`NEES_CONSISTENT` for a filter whose particle covariance is
    honest. The median, since a collapsed particle cloud gives single values of 1e6 and more; NaN unless every run
    stored the column (results saved before it), or where no value is finite."""
    if not res or any("pos_nees" not in r.vehicles for r in res):
        return math.nan
    a = _vehicle_values(res, names, mp, fusion_start, "pos_nees")
    return float(np.median(a)) if a.size else math.nan


SUMMARY_FILES: tuple[str, ...] = (SUMMARY_PARQUET, SUMMARY_JSON)
"""The files :func:`aggregate` writes (their stale temp files are removed by the next aggregation)."""


def _write_summary(out: Path, s: Summary) -> None:
    import pyarrow as pa
    import pyarrow.parquet as pq

    tab = pa.table({k: pa.array(v.tolist()) if v.dtype == object else pa.array(v) for k, v in s.table.items()})
    tmp = temp_path(out / SUMMARY_PARQUET)
    try:
        pq.write_table(tab, tmp)
        os.replace(tmp, out / SUMMARY_PARQUET)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    per_step = {k: [None if isinstance(x, float) and not math.isfinite(x) else x for x in v.tolist()]
                for k, v in s.table.items()}
    head = [{k: (None if isinstance(x, float) and not math.isfinite(x) else x) for k, x in r.items()}
            for r in s.headline]
    paired = {k: [None if isinstance(x, float) and not math.isfinite(x) else x for x in v]
              for k, v in s.paired.items()}
    _write_json(out / SUMMARY_JSON, {"config": s.config, "headline": head, "per_step": per_step,
                                     "per_step_paired": paired, "sensor_models": _finite_or_none(s.sensor)})


def load_summary(out_dir: str | Path) -> Summary:
    """Read ``summary.parquet`` / ``summary.json`` back (written by :func:`aggregate`)."""
    import pyarrow.parquet as pq

    out = Path(out_dir)
    pj, pp = out / SUMMARY_JSON, out / SUMMARY_PARQUET
    if not (pj.is_file() and pp.is_file()):
        raise CacheError(f"{out}: no {SUMMARY_PARQUET}/{SUMMARY_JSON}; run `mmslam report {out}` or the "
                         "ablation to create them")
    try:
        t = pq.read_table(pp)
        table = {c: t.column(c).to_numpy(zero_copy_only=False) for c in t.column_names}
        j = json.loads(pj.read_text())
    except Exception as e:
        raise CacheError(f"{out}: unreadable summary ({_one_line(e)}); run `mmslam report {out}` to rebuild") from None
    for k in ("variant", "map", "type", "quantity"):
        table[k] = np.asarray(table[k], dtype=object)
    head = [{k: (math.nan if x is None else x) for k, x in r.items()} for r in j["headline"]]
    paired = {k: [math.nan if x is None and k in ("diff", "ci") else x for x in v]
              for k, v in j.get("per_step_paired", {}).items()}
    return Summary(table, head, j["config"], paired, j.get("sensor_models", {}))


def _finite_or_none(x: Any) -> Any:
    """``x`` with every non-finite float replaced by None (JSON has no NaN)."""
    if isinstance(x, dict):
        return {k: _finite_or_none(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_finite_or_none(v) for v in x]
    return None if isinstance(x, float) and not math.isfinite(x) else x
