"""What the filter was given under each sensor model, and the sensor-model arms compared (issue 24).

Every run stores, for evaluation only, how many of its measurements came from each kind of path
(``Result.meta["measurement_counts"]``: per step and vehicle, the registered types, ``OTHER`` and
``clutter``, i.e. false alarms with no originating path) and, under ``sensor.model = "estimated"``, the
channel estimator's counts (``meta["estimator_counts"]``: estimates, detected, merged, false, missed,
suppressed).
:func:`measurement_rows` averages them per vehicle-step over the runs of each variant (or grid arm);
:func:`sensor_pairs` gives, for an ablation whose grid varies ``sensor.model``, the paired difference of
the fused map's scores between an arm and the same variant's reference-model arm (``link``, else
``constant``) over the seeds both ran, with its 95% CI: e.g.

    mmslam ablate paper --source sionna --variants proposed --grid sensor.model=link,estimated --mc 10
"""
from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from mmslam.pipelines.ablate.options import Job, parse_label
from mmslam.pipelines.ablate.stats import ci95

SENSOR_KEY = "sensor.model"
REFERENCE_MODELS: tuple[str, ...] = ("link", "constant")
"""The arm an other sensor model is compared with, first present wins."""
PAIRED_SCORES: tuple[str, ...] = ("gospa_VA", "gospa_VS", "pos_rmse")
"""Fused-map scores (per-run: mean over the headline steps) compared between sensor-model arms."""


def _arm_model(arm: Sequence[str]) -> str | None:
    for kv in arm:
        k, _, v = kv.partition("=")
        if k.strip() == SENSOR_KEY:
            return v.strip().strip('"')
    return None


def sensor_model(label: str, spec: Mapping[str, Any], metas: Sequence[Mapping[str, Any]] = ()) -> str:
    """The sensor model of a variant label: what its runs recorded, else its grid arm, else the
    ablation's ``--set``, else the scenario's ``sensor.model``."""
    for m in metas:
        mc = m.get("measurement_counts")
        if isinstance(mc, Mapping) and mc.get("model"):
            return str(mc["model"])
    model = _arm_model(parse_label(label)[1]) or _arm_model(spec.get("sets", []))
    return model or str(spec.get("scenario", {}).get("sensor", {}).get("model", "constant"))


def _mean_counts(metas: Sequence[Mapping[str, Any]], key: str) -> dict[str, float] | None:
    """Mean per (step, vehicle) of ``meta[key]["per_step_vehicle"]`` over runs, by column; None if no run has it.

    Runs may store different columns (a resumed ablation whose older runs predate a column, e.g. the
    estimator's ``suppressed``): each column is the mean over the (step, vehicle) rows of the runs that
    have it, in the order first seen."""
    sums: dict[str, float] = {}
    rows: dict[str, int] = {}
    for m in metas:
        c = m.get(key)
        if not isinstance(c, Mapping) or "per_step_vehicle" not in c:
            continue
        cols = list(c["columns"])
        block = np.asarray(c["per_step_vehicle"], float).reshape(-1, len(cols))
        for j, col in enumerate(cols):
            sums[col] = sums.get(col, 0.0) + float(block[:, j].sum())
            rows[col] = rows.get(col, 0) + block.shape[0]
    if not sums:
        return None
    return {col: sums[col] / rows[col] if rows[col] else math.nan for col in sums}


def _mean_link_pd(metas: Sequence[Mapping[str, Any]]) -> dict[str, float] | None:
    """Type -> mean over the runs of the p_D taken from the link budget (``meta['p_detect_from_link']``), or None."""
    vals: dict[str, list[float]] = {}
    for m in metas:
        for t, v in (m.get("p_detect_from_link") or {}).items():
            vals.setdefault(t, []).append(float(v["p_detect"]))
    return {t: float(np.mean(v)) for t, v in vals.items()} or None


def measurement_rows(jobs: Mapping[Job, Any], labels: Sequence[str], spec: Mapping[str, Any]) -> list[dict[str, Any]]:
    """Per label: ``variant`` (the label), ``model``, ``runs``, ``measurements`` (mean count per
    vehicle-step of each origin column; None for runs stored before the counts existed),
    ``estimator`` (the estimator's counts per vehicle-step, None unless ``estimated``) and
    ``p_detect_from_link`` (type -> the filter's p_D taken from the link budget, mean over runs; None
    where no type took it: the ``constant`` model, ``filter.types.<T>.p_detect_source = value``)."""
    rows = []
    for lab in labels:
        metas = [jobs[j].meta for j in sorted(jobs) if j.label == lab]
        rows.append({"variant": lab, "model": sensor_model(lab, spec, metas), "runs": len(metas),
                     "measurements": _mean_counts(metas, "measurement_counts"),
                     "estimator": _mean_counts(metas, "estimator_counts"),
                     "p_detect_from_link": _mean_link_pd(metas)})
    return rows


def link_pd_notice(rows: Sequence[Mapping[str, Any]]) -> str | None:
    """One line naming each label's p_D taken from the link budget (:func:`measurement_rows`), or None."""
    parts = [f"{r['variant']}: " + ", ".join(f"{t} {v:.2f}" for t, v in r["p_detect_from_link"].items())
             for r in rows if r.get("p_detect_from_link")]
    return ("p_D from the link budget (filter.types.<T>.p_detect_source = link): " + "; ".join(parts)) if parts else None


def _reference_label(label: str, labels: Sequence[str], models: Mapping[str, str]) -> str | None:
    """The label with the same variant and grid settings but the reference sensor model, if any."""
    variant, arm = parse_label(label)
    rest = tuple(kv for kv in arm if _arm_model([kv]) is None)
    for ref in REFERENCE_MODELS:
        if models[label] == ref:
            return None
        for cand in labels:
            v, a = parse_label(cand)
            if v == variant and cand != label and models[cand] == ref and \
                    tuple(kv for kv in a if _arm_model([kv]) is None) == rest:
                return cand
    return None


def sensor_pairs(per_run: Mapping[str, Mapping[int, Mapping[str, Mapping[str, float]]]],
                 models: Mapping[str, str], map_name: str = "fused") -> list[dict[str, Any]]:
    """Paired differences ``label - reference`` of :data:`PAIRED_SCORES` on ``map_name`` over the common
    seeds, for every label with a reference-model twin (:data:`REFERENCE_MODELS`).

    Args:
        per_run: label -> seed -> map -> score (the per-run scores of the aggregation).
        models: label -> sensor model (:func:`sensor_model`).

    Returns:
        Rows ``variant, reference, model, reference_model, n`` and per score ``<score>``,
        ``<score>_ref`` (means over the common seeds), ``<score>_diff``, ``<score>_diff_ci`` (95% Student-t
        half-width), ``<score>_sig`` (the interval excludes 0).
    """
    labels = list(per_run)
    out = []
    for lab in labels:
        ref = _reference_label(lab, labels, models)
        if ref is None:
            continue
        common = sorted(s for s in set(per_run[lab]) & set(per_run[ref])
                        if map_name in per_run[lab][s] and map_name in per_run[ref][s])
        row: dict[str, Any] = {"variant": lab, "reference": ref, "model": models[lab],
                               "reference_model": models[ref], "n": len(common)}
        for q in PAIRED_SCORES:
            a = np.array([per_run[lab][s][map_name][q] for s in common], float)
            b = np.array([per_run[ref][s][map_name][q] for s in common], float)
            row[q] = float(a.mean()) if a.size else math.nan
            row[q + "_ref"] = float(b.mean()) if b.size else math.nan
            mean, half = ci95(a - b)
            row[q + "_diff"], row[q + "_diff_ci"] = mean, half
            row[q + "_sig"] = bool(math.isfinite(half) and abs(mean) > half)
        out.append(row)
    return out
