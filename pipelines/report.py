"""The ablation report: figures + one self-contained HTML file, regenerated from stored results.

:func:`write_report` re-aggregates the stored jobs of an ablation directory
(:func:`mmslam.pipelines.ablate.aggregate`), draws every figure of
:mod:`mmslam.pipelines.figures` into ``DIR/figures/*.png`` and writes ``DIR/report.html`` with
the figures embedded as base64 PNG, the summary table, the scenario parameters, the software
versions and the command that reproduces the ablation.

The summary table is machine-readable: ``<table id="summary">`` rows carry ``data-variant`` and
``data-map``, cells ``data-col`` (``gospa_VA``, ``gospa_SP``, ``gospa_VS``, ``pos_rmse``, ``pos_nees``,
``card_VS``, ``wall_time_s``, ``runs``) and ``data-value`` (the full-precision mean); scored
cells show ``mean ± 95% CI half-width``. ``<table id="paired">`` gives the paired differences to
baseline (same seeds) with their 95% CI and whether each is significant.
"""
from __future__ import annotations

import base64
import datetime as _dt
import html
import importlib.metadata
import json
import math
import platform
from pathlib import Path
from typing import Any

from mmslam.pipelines.ablate import (NEES_CONSISTENT, SCORED, Job, Summary, aggregate, is_finished, job_dir,
                                     parse_label, plan_jobs, read_ablation, spec_arms)
from mmslam.pipelines.ablate.store import FIGURE_NAMES, FIGURES_DIR, REPORT_FILE, check_ablation_outputs  # noqa: F401

HEADLINE_COLUMNS: tuple[tuple[str, str], ...] = (
    ("gospa_VA", "GOSPA VA [m]"), ("gospa_SP", "GOSPA SP [m]"), ("gospa_VS", "GOSPA VS [m]"),
    ("pos_rmse", "position RMSE [m]"), ("pos_nees", f"position NEES (median; {NEES_CONSISTENT:.2f} consistent)"),
    ("card_VS", "VS cardinality"), ("wall_time_s", "wall time / run [s]"),
    ("runs", "runs"),
)
"""(key, header) of the summary table's number columns, in order."""


def software_versions() -> dict[str, str]:
    """Versions of Python and the libraries that shape the results (``not installed`` if absent)."""
    out = {"python": platform.python_version()}
    for pkg in ("mmslam", "numpy", "scipy", "pyarrow", "matplotlib", "sionna-rt", "mitsuba", "drjit",
                "dask", "distributed"):
        try:
            out[pkg] = importlib.metadata.version(pkg)
        except importlib.metadata.PackageNotFoundError:
            out[pkg] = "not installed"
    out["platform"] = platform.platform()
    return out


def make_figures(out_dir: str | Path, summary: Summary) -> dict[str, Path]:
    """Draw every figure into ``out_dir/figures``; returns name -> PNG path (in report order).

    The top-down maps show the lowest finished seed of each variant.
    """
    from mmslam.pipelines import figures as F
    from mmslam.scenes.scenario import scenario_from_resolved
    from mmslam.slam.filter.result import Result

    out = Path(out_dir)
    fdir = out / FIGURES_DIR
    spec = read_ablation(out)
    made: dict[str, Path] = {}
    plots = (("fig2a_gospa_vs", lambda: F.fig_gospa(summary, "VS")),  # names: FIGURE_NAMES
             ("fig2b_gospa_va", lambda: F.fig_gospa(summary, "VA")),
             ("fig3_position_rmse", lambda: F.fig_position_rmse(summary)),
             ("fig2a_paired_vs", lambda: F.fig_paired(summary, "gospa_VS")),
             ("fig2b_paired_va", lambda: F.fig_paired(summary, "gospa_VA")),
             ("fig3_paired_position", lambda: F.fig_paired(summary, "pos_err")),
             ("gospa_sp", lambda: F.fig_gospa(summary, "SP")),
             ("cardinality_vs", lambda: F.fig_cardinality(summary, "VS")),
             ("cardinality_va", lambda: F.fig_cardinality(summary, "VA")))
    for name, make in plots:
        made[name] = F.save_figure(make(), fdir / f"{name}.png")
    scn = scenario_from_resolved(spec["scenario"], str(out / "ablation.json"))
    for label in summary.variants:
        v, arm = parse_label(label)
        seeds = sorted(int(s) for s in spec.get("seeds", []) if is_finished(out, Job(v, int(s), arm)))
        if not seeds:
            continue
        res = Result.load(job_dir(out, Job(v, seeds[0], arm)))
        made[f"map_{label}"] = F.save_figure(F.fig_map(res, scn), fdir / f"map_{label}.png")
    return made


FIGURE_CAPTIONS = {
    "fig2a_gospa_vs": "Fig. 2a: mean GOSPA of the VS map (fused at the BS) vs time step; shaded: ±1 std over runs.",
    "fig2b_gospa_va": "Fig. 2b: mean GOSPA of the VA map (fused at the BS) vs time step; shaded: ±1 std over runs.",
    "fig3_position_rmse": "Fig. 3: vehicle position RMSE over Monte Carlo runs and vehicles vs time step.",
    "fig2a_paired_vs": "Fig. 2a, paired: per step, fused VS GOSPA of each variant minus baseline's on the same "
                       "seeds (mean, 95% Student-t band); filled markers: the band excludes 0.",
    "fig2b_paired_va": "Fig. 2b, paired: per step, fused VA GOSPA minus baseline's (mean, 95% band); filled "
                       "markers: significant.",
    "fig3_paired_position": "Fig. 3, paired: per step, the position error (mean over vehicles) minus baseline's on "
                            "the same seeds (mean, 95% band); filled markers: significant.",
    "gospa_sp": "Mean GOSPA of the SP map (fused at the BS) vs time step.",
    "cardinality_vs": "Estimated number of VSs (PHD mass of the fused VS map) vs time step, mean over runs; "
                      "dotted: the true number of vehicles. A merge of two vehicles shows as a drop.",
    "cardinality_va": "Estimated number of VAs (PHD mass of the fused VA map) vs time step, mean over runs; "
                      "dotted: the true number of VAs seen so far.",
}


def _fmt(x: Any, col: str) -> str:
    if isinstance(x, (int,)) and not isinstance(x, bool):
        return str(x)
    try:
        f = float(x)
    except (TypeError, ValueError):
        return html.escape(str(x))
    if not math.isfinite(f):
        return "n/a"
    return f"{f:.2f}" if col == "wall_time_s" else f"{f:.3f}"


def _cell(r: dict[str, Any], k: str) -> str:
    """``mean ± CI`` for scored columns (CI = 95% half-width over runs), the plain number otherwise."""
    text = _fmt(r.get(k), k)
    ci = r.get(k + "_ci")
    if k in SCORED and ci is not None and isinstance(ci, float) and math.isfinite(ci):
        text += f" ± {ci:.2f}"
    return text


def paired_rows(summary: Summary) -> list[dict[str, Any]]:
    """One row per (variant, map, score) that has a reference: difference, CI, significance, sentence."""
    out = []
    for r in summary.headline:
        if not r.get("reference"):
            continue
        for q in SCORED:
            d, ci, sig = r.get(q + "_diff"), r.get(q + "_diff_ci"), r.get(q + "_sig")
            if d is None or not isinstance(d, float) or not math.isfinite(d):
                continue
            if sig:
                verdict = f"{'lower' if d < 0 else 'higher'} than {r['reference']} (significant at 95%)"
            elif ci is not None and math.isfinite(ci):
                verdict = f"no significant difference to {r['reference']}"
            else:
                verdict = "too few runs for an interval"
            out.append({"variant": r["variant"], "map": r["map"], "score": q, "diff": d, "ci": ci,
                        "significant": bool(sig), "verdict": verdict})
    return out


def _paired_html(summary: Summary) -> str:
    rows = []
    for p in paired_rows(summary):
        ci = "n/a" if not math.isfinite(p["ci"]) else f"± {p['ci']:.3f}"
        rows.append(f'<tr data-variant="{html.escape(p["variant"])}" data-map="{html.escape(p["map"])}" '
                    f'data-score="{p["score"]}" data-significant="{str(p["significant"]).lower()}">'
                    f'<td>{html.escape(p["variant"])}</td><td>{html.escape(p["map"])}</td><td>{p["score"]}</td>'
                    f'<td>{p["diff"]:+.3f}</td><td>{ci}</td>'
                    f'<td style="text-align:left">{html.escape(p["verdict"])}</td></tr>')
    return ('<table id="paired"><thead><tr><th>variant</th><th>map</th><th>score</th><th>paired difference</th>'
            f'<th>95% CI</th><th>verdict</th></tr></thead><tbody>{"".join(rows)}</tbody></table>')


def _num(x: Any, nd: int = 2) -> str:
    try:
        f = float(x)
    except (TypeError, ValueError):
        return "n/a"
    return f"{f:.{nd}f}" if math.isfinite(f) else "n/a"


def _sensor_html(summary: Summary) -> str:
    """``<table id="measurements">``: per variant (grid arm) its sensor model and the mean number of
    measurements per vehicle-step by origin (landmark type, OTHER path, clutter / false alarm), with
    the channel estimator's merged, missed and suppressed counts (suppressed: dropped by the non-maximum
    suppression before the filter; "n/a" for runs stored before it); ``<table id="sensor-pairs">``: the paired
    differences between sensor-model arms (:mod:`mmslam.pipelines.ablate.sensor_models`)."""
    sm = summary.sensor or {}
    rows = sm.get("measurements") or []
    if not rows:
        return "<p>No measurement counts stored (results from before they were recorded).</p>"
    cols: list[str] = []
    for r in rows:
        for c in (r.get("measurements") or {}):
            if c not in cols:
                cols.append(c)
    est_cols = ("merged", "missed", "suppressed")
    body = []
    for r in rows:
        m, e = r.get("measurements") or {}, r.get("estimator") or {}
        cells = "".join(f'<td data-col="{html.escape(c)}">{_num(m.get(c))}</td>' for c in cols)
        cells += "".join(f'<td data-col="est_{c}">{_num(e.get(c)) if e else "-"}</td>' for c in est_cols)
        body.append(f'<tr data-variant="{html.escape(str(r["variant"]))}" data-model="{html.escape(str(r["model"]))}">'
                    f'<td>{html.escape(str(r["variant"]))}</td><td>{html.escape(str(r["model"]))}</td>'
                    f'<td>{r.get("runs", "")}</td>{cells}</tr>')
    head = "".join(f"<th>{html.escape(c)}</th>" for c in cols) + ("<th>merged (estimator)</th><th>missed (estimator)</th>"
                                                            "<th>suppressed (estimator)</th>")
    out = ('<table id="measurements"><thead><tr><th>variant</th><th>sensor model</th><th>runs</th>'
           f'{head}</tr></thead><tbody>{"".join(body)}</tbody></table>')
    pairs = sm.get("pairs") or []
    if pairs:
        prow = []
        for p in pairs:
            for q, name in (("gospa_VA", "fused VA GOSPA [m]"), ("gospa_VS", "fused VS GOSPA [m]"),
                            ("pos_rmse", "position RMSE [m]")):
                ci = p.get(q + "_diff_ci")
                sig = "significant" if p.get(q + "_sig") else "not significant"
                prow.append(f'<tr data-variant="{html.escape(str(p["variant"]))}" data-score="{q}">'
                            f'<td>{html.escape(str(p["variant"]))}</td><td>{html.escape(str(p["reference"]))}</td>'
                            f'<td>{name}</td><td>{_num(p.get(q))}</td><td>{_num(p.get(q + "_ref"))}</td>'
                            f'<td>{_num(p.get(q + "_diff"), 3)}</td><td>± {_num(ci, 3)}</td><td>{p.get("n")}</td>'
                            f'<td style="text-align:left">{sig}</td></tr>')
        out += ('<h3>Sensor models compared</h3><p>Per seed, the arm minus the same variant\'s arm with the '
                'reference sensor model (link, else constant); mean and 95% CI over the common seeds.</p>'
                '<table id="sensor-pairs"><thead><tr><th>arm</th><th>reference</th><th>score</th><th>arm</th>'
                '<th>reference</th><th>paired difference</th><th>95% CI</th><th>seeds</th><th>verdict</th></tr>'
                f'</thead><tbody>{"".join(prow)}</tbody></table>')
    return out


def summary_rows(summary: Summary) -> list[dict[str, Any]]:
    """The headline rows (variant, map, :data:`HEADLINE_COLUMNS`), in table order."""
    return list(summary.headline)


def _summary_html(summary: Summary) -> str:
    head = "".join(f"<th>{html.escape(h)}</th>" for _, h in HEADLINE_COLUMNS)
    rows = []
    for r in summary_rows(summary):
        cells = "".join(
            f'<td data-col="{k}" data-value="{html.escape(repr(r.get(k)))}">{_cell(r, k)}</td>'
            for k, _ in HEADLINE_COLUMNS)
        rows.append(f'<tr data-variant="{html.escape(r["variant"])}" data-map="{html.escape(r["map"])}">'
                    f'<td>{html.escape(r["variant"])}</td><td>{html.escape(r["map"])}</td>{cells}</tr>')
    return (f'<table id="summary"><thead><tr><th>variant</th><th>map</th>{head}</tr></thead>'
            f'<tbody>{"".join(rows)}</tbody></table>')


def _flatten(d: Any, prefix: str = "") -> list[tuple[str, str]]:
    out: list[tuple[str, str]] = []
    if isinstance(d, dict):
        for k, v in d.items():
            out += _flatten(v, f"{prefix}.{k}" if prefix else str(k))
    elif isinstance(d, list) and d and all(isinstance(x, dict) for x in d):
        for x in d:
            name = x.get("name", "")
            out.append((f"{prefix}[{name}]", json.dumps({k: v for k, v in x.items() if k != "name"})))
    else:
        out.append((prefix, json.dumps(d)))
    return out


def _kv_table(pairs: list[tuple[str, str]], table_id: str) -> str:
    body = "".join(f"<tr><th>{html.escape(k)}</th><td><code>{html.escape(v)}</code></td></tr>" for k, v in pairs)
    return f'<table id="{table_id}" class="kv"><tbody>{body}</tbody></table>'


_CSS = """
body{font-family:system-ui,sans-serif;max-width:1100px;margin:2em auto;padding:0 1em;color:#222}
table{border-collapse:collapse;margin:1em 0;font-size:0.9em}
th,td{border:1px solid #ccc;padding:3px 8px;text-align:right}
th{background:#f3f3f3} table.kv th,table.kv td{text-align:left}
figure{display:inline-block;margin:0.5em;max-width:48%;vertical-align:top}
figure img{max-width:100%} figcaption{font-size:0.85em}
pre{background:#f6f6f6;padding:0.6em;overflow-x:auto} .warn{color:#a00}
.mmslam-viewer svg { max-width: 100%; height: auto; } .mmslam-viewer .legend { font-size: 0.85em; color: #444; }
"""


def _variants_html(variants: list[str]) -> str:
    """``<table id="variants">``: each variant's legend label and what it runs (:class:`VariantSpec`)."""
    from mmslam.slam.specs.variants import variant_names, get_variant

    rows = []
    for v in variants:
        if v not in variant_names():  # a variant registered by a plugin that is not loaded now
            rows.append(f'<tr data-variant="{html.escape(v)}"><td>{html.escape(v)}</td><td></td><td>not registered '
                        "in this process</td></tr>")
            continue
        s = get_variant(v)
        rows.append(f'<tr data-variant="{html.escape(v)}"><td>{html.escape(v)}</td><td>{html.escape(s.label)}</td>'
                    f"<td>{html.escape(s.describe())}</td></tr>")
    return ('<table id="variants"><thead><tr><th>variant</th><th>label</th><th>maps and countermeasures</th></tr></thead><tbody>'
            + "".join(rows) + "</tbody></table>")


def viewers_html(out_dir: str | Path, summary: Summary) -> str:
    """The step viewers of the report: one per variant (arm), on its lowest finished seed.

    Each is a :func:`mmslam.slam.eval.viewer.viewer_html` fragment; the traced paths come from the
    ablation's cache when it is still at the recorded ``cache_dir`` with the same config hash (else
    the viewer says so and shows no paths). The renderer script is embedded once.
    """
    from mmslam.slam.eval.viewer import VIEWER_JS, viewer_data, viewer_html
    from mmslam.scenes.scenario import scenario_from_resolved
    from mmslam.slam.filter.result import Result

    out = Path(out_dir)
    spec = read_ablation(out)
    scn = scenario_from_resolved(spec["scenario"], str(out / "ablation.json"))
    paths = _cache_paths(spec)
    parts = []
    for i, label in enumerate(summary.variants):
        v, arm = parse_label(label)
        seeds = sorted(int(s) for s in spec.get("seeds", []) if is_finished(out, Job(v, int(s), arm)))
        if not seeds:
            continue
        res = Result.load(job_dir(out, Job(v, seeds[0], arm)))
        data = viewer_data(res, scn, paths, title=f"{label}, seed {seeds[0]}")
        parts.append(f'<details{" open" if i == 0 else ""}><summary>{html.escape(label)} (seed {seeds[0]})</summary>'
                     f"{viewer_html(data, element_id=f'viewer-{label}', script=False)}</details>")
    if not parts:
        return ""
    return "".join(parts) + f"<script>{VIEWER_JS}</script>"


def _cache_paths(spec: dict[str, Any]) -> dict[str, Any] | None:
    """The ``paths`` table of the ablation's cache, or None if it moved, changed or cannot be read."""
    from mmslam.errors import MmslamError
    from mmslam.raytrace.cache import load_cache

    d = spec.get("cache_dir")
    if not d or not Path(d).is_dir():
        return None
    try:
        c = load_cache(d)
    except MmslamError:
        return None
    if spec.get("config_hash") and c.manifest.get("config_hash") != spec.get("config_hash"):
        return None
    return c.paths


def render_html(out_dir: str | Path, summary: Summary, figures: dict[str, Path]) -> str:
    """The report as one HTML string (figures inlined as base64 PNG, step viewers as inline SVG + script)."""
    out = Path(out_dir)
    spec = read_ablation(out)
    cfg = summary.config
    grid = plan_jobs(spec.get("variants", []), int(spec.get("mc", 0)), int(spec.get("seed0", 0)), spec_arms(spec))
    missing = [j.name for j in grid if not is_finished(out, j)]
    figs = []
    for name, path in figures.items():
        b64 = base64.b64encode(Path(path).read_bytes()).decode("ascii")
        cap = FIGURE_CAPTIONS.get(name) or (f"Top-down map of variant {name[4:]} (lowest seed) at the last "
                                            "step: hollow = truth, x = estimates; solid = true, dashed = "
                                            "estimated trajectories.")
        figs.append(f'<figure id="fig-{name}"><img alt="{html.escape(name)}" src="data:image/png;base64,{b64}">'
                    f"<figcaption>{html.escape(cap)}</figcaption></figure>")
    abl = [("scenario", str(spec.get("scenario_name"))), ("source", str(spec.get("source"))),
           ("trace config hash", str(spec.get("config_hash"))), ("variants", ",".join(spec.get("variants", []))),
           ("Monte Carlo runs (seeds)", f"{spec.get('mc')} ({int(spec.get('seed0', 0))}.."
                                        f"{int(spec.get('seed0', 0)) + int(spec.get('mc', 1)) - 1})"),
           ("--set", " ".join(spec.get("sets", [])) or "none"), ("--grid", " ".join(spec.get("grid", [])) or "none"),
           ("particles", str(spec.get("particles"))), ("time steps", str(spec.get("steps"))),
           ("fusion start (GOSPA / RMSE averaged over steps >=)", str(cfg.get("fusion_start")))]
    warn = (f'<p class="warn">Incomplete: {len(missing)} of {len(grid)} jobs missing '
            f"({html.escape(', '.join(missing[:10]))}{' ...' if len(missing) > 10 else ''}); re-run the "
            "command below to finish them.</p>") if missing else ""
    vers = software_versions()
    now = _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    return f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>mmslam ablation: {html.escape(str(spec.get('scenario_name')))}</title>
<style>{_CSS}</style></head><body>
<h1>Cooperative MM-PHD-SLAM with vehicle scatterers: ablation report</h1>
<p>Scenario <b>{html.escape(str(spec.get('scenario_name')))}</b>, {html.escape(str(spec.get('source')))} paths,
{len(grid)} jobs (variants x seeds). Generated {now} from the stored results in <code>{html.escape(str(out.resolve()))}</code>.</p>
{warn}
<h2>Summary</h2>
<p>Mean GOSPA (p = 2, c = {html.escape(str(_eval(spec, 'gospa_c')))} m, alpha = 2) per landmark type and map,
and position RMSE, both over all runs and the time steps k &ge; {cfg.get('fusion_start')} (map fusion start).
Vehicle rows: that vehicle's local map and position error; <i>fused</i>: the BS map and all vehicles' positions.
Wall time: mean per filter run (one variant, one seed, all vehicles). ± : half-width of the 95% Student-t
confidence interval of the mean over runs (per-run mean GOSPA, per-run RMSE). VS cardinality: mean PHD mass of
the map (estimated number of vehicles).</p>
{_summary_html(summary)}
<h3>Paired differences to baseline</h3>
<p>Per run (same seed: same measurements and prior), score of the variant minus score of baseline; mean and 95% CI
over runs. A difference whose interval contains 0 is reported as not significant.</p>
{_paired_html(summary)}
<h2>Measurements</h2>
<p>What each variant's filter was given: mean number of measurements per vehicle and step by the path it came
from (evaluation labels, never used by the filter; <i>clutter</i>: false alarms with no originating path). Under
the <code>estimated</code> sensor model these are the channel estimator's estimates, labelled by the rays in
their resolution cell; <i>merged</i>: estimates whose cell holds rays of two or more landmarks, <i>missed</i>:
landmarks of the paths table no estimate is labelled with.</p>
{_sensor_html(summary)}
<h2>Variants</h2>
{_variants_html(spec.get("variants", []))}
<h2>Figures</h2>
{''.join(figs)}
<h2>Step through a run</h2>
<p>Per time step: true (dot, solid) and estimated (plus, dashed) vehicle positions and trajectories, the estimated
landmarks (x) of the chosen map against the truth (hollow), and the traced paths of that step. One run per
variant (its lowest seed); drag the slider or press play.</p>
{viewers_html(out, summary)}
<h2>Reproduce</h2>
<pre id="command">{html.escape(str(spec.get('command', '')))}</pre>
<p>Regenerate this report from the stored results: <code>mmslam report {html.escape(str(out))}</code></p>
<h2>Ablation settings</h2>
{_kv_table(abl, 'settings')}
<h2>Scenario parameters</h2>
{_kv_table(_flatten(spec.get('scenario', {})), 'scenario')}
<h2>Software</h2>
{_kv_table(list(vers.items()), 'versions')}
</body></html>
"""


def _eval(spec: dict[str, Any], key: str) -> Any:
    return spec.get("scenario", {}).get("evaluation", {}).get(key, "?")


def write_report(out_dir: str | Path) -> Path:
    """Re-aggregate the stored jobs, redraw the figures and write ``out_dir/report.html``.

    Raises:
        CacheError: ``out_dir`` is missing, holds no ablation or no finished job.
    """
    from mmslam.outputs import atomic_write_bytes, locked

    out = Path(out_dir)
    read_ablation(out)  # a one-line error, before the lock file is made next to a wrong path
    with locked(out, "mmslam command"):
        check_ablation_outputs(out)
        summary = aggregate(out)
        figures = make_figures(out, summary)
        text = render_html(out, summary, figures)
        return atomic_write_bytes(out / REPORT_FILE, text.encode("utf-8"), fsync=False)


CONSOLE_COLUMNS: tuple[tuple[str, str], ...] = tuple(c for c in HEADLINE_COLUMNS if c[0] != "pos_nees")
"""The columns of the console summary (:func:`summary_console_table`): the report's but the NEES, which an 80-column
terminal has no room for (it is in ``summary.json`` and the report)."""

_CONSOLE_HEADERS = {"gospa_VA": "VA", "gospa_SP": "SP", "gospa_VS": "VS", "pos_rmse": "pos RMSE",
                    "card_VS": "VS card", "wall_time_s": "s/run", "runs": "runs"}


def summary_console_table(summary: Summary, title: str = "Summary", width: int | None = None) -> Any:
    """The summary table as a :class:`rich.table.Table` (for the CLI), for a console ``width`` wide.

    When one line per row does not fit ``width`` (an 80-column terminal), the table turns compact
    instead of letting rich squeeze columns to nothing: each number's ``±`` interval goes on a second
    line of its cell, two-word headers on two lines, and a long variant (grid-arm) label folds onto
    more lines; the variant and map columns always stay (``tests/test_pipelines.py`` renders it 80
    columns wide)."""
    from rich.markup import escape
    from rich.table import Table

    fs = summary.config.get("fusion_start")
    rows = summary_rows(summary)
    heads = ["variant", "map"] + [_CONSOLE_HEADERS[k] for k, _ in CONSOLE_COLUMNS]
    cells = [[str(r["variant"]), str(r["map"])] + [_cell(r, k) for k, _ in CONSOLE_COLUMNS] for r in rows]

    def natural(j: int, compact: bool) -> int:
        words = [heads[j]] + [c[j] for c in cells]
        if compact:
            words = [w for t in words for w in t.replace("± ", "±").split()]
        return max(map(len, words))

    n = len(heads)
    wide = sum(natural(j, False) for j in range(n)) + 3 * n + 1  # one space of padding each side, borders
    compact = width is not None and wide > width
    t = Table(title=escape(f"{title}\nmean GOSPA [m] and position RMSE [m] over runs and steps k >= {fs}"))
    if compact:
        rest = sum(natural(j, True) for j in range(1, n)) + 3 * n + 1
        label_w = max(min(natural(0, False), width - rest), 8)  # at least "proposed"
        t.add_column("variant", width=label_w, overflow="fold")
        t.add_column("map", no_wrap=True)
        for k, _ in CONSOLE_COLUMNS:
            t.add_column(_CONSOLE_HEADERS[k].replace(" ", "\n"), justify="right", no_wrap=True)
        for c in cells:
            t.add_row(escape(c[0]), escape(c[1]), *[escape(x.replace(" ± ", "\n±")) for x in c[2:]])
    else:
        t.add_column("variant")
        t.add_column("map")
        for k, _ in CONSOLE_COLUMNS:
            t.add_column(_CONSOLE_HEADERS[k], justify="right", no_wrap=True)
        for c in cells:
            t.add_row(*[escape(x) for x in c])
    return t


__all__ = ["write_report", "make_figures", "render_html", "software_versions", "summary_console_table",
           "summary_rows", "paired_rows", "HEADLINE_COLUMNS", "CONSOLE_COLUMNS"]
