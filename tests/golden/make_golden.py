"""Golden end-to-end fixtures: the `paper` reference runs, stored to guard refactors at 1e-9.

What is stored (``tests/golden/*.npz``, written by this script from the code as it is):

- ``analytic_<case>.npz``: one cooperative run per case of :data:`CASES` on the closed-form paths of
  the ``paper`` preset (:class:`~mmslam.raytrace.analytic.AnalyticSource`, the preset's truth with
  process noise): every variant (``odometry``, ``baseline``, ``cm1``, ``proposed``) at a few small
  particle counts, plus two runs with non-default switches (link sensor model, Beta p_D, label
  averaging; gated VS reduction, a separate VA merge gate) so their code paths are guarded too;
- ``sionna_paths.npz``: the true states and the ``paths`` table of a short Sionna RT trace of
  ``paper`` (:data:`SIONNA_STEPS` steps, depth 1, 10^6 rays per source, seed 0, LLVM on the CPU);
- ``sionna_<variant>.npz``: a run of each fusion variant on those stored Sionna paths;
- ``city_paths.npz`` and ``city_<case>.npz``: the same for the ``canyon`` preset (:data:`CITY_STEPS` steps of its
  Sionna RT trace, same settings) and the runs of :data:`CITY_CASES` on it, which take the city defaults ``paper``
  pins away (learnt p_D, exclusive VA association, Bernoulli missed detections, the VA heavy tail, the weight offset
  at a share 0.2 and merge gate 6,
  visibility-weighted label averaging, the car-body VS model of a traced source).

Per run (:func:`snapshot`): every column of the run's :class:`~mmslam.slam.filter.result.Result` tables
(``res/<table>/<column>``: vehicle estimates and errors; GOSPA with its localisation / missed /
false parts, cardinality and counts per step, map and type; the extracted landmark estimates), and
per step the vehicles' :class:`StepEstimate` (mean, upper triangle of the covariance, ESS, whether
it resampled) and the fused BS map of every type, keyed by the type's name (the live components'
weights, means, upper-triangle covariances, and Beta p_D parameters / labels where the run keeps
them; ``fused/<type>/step`` says which step each component row belongs to).

``tests/test_golden.py`` re-runs every case and compares with :func:`compare`: float arrays at
``|got - want| <= RTOL |want| + ATOL`` (1e-9 relative; the 1e-12 absolute floor, in the array's own
units (m, rad, m^2, PHD weight), only matters for values within ~1e-3 of zero, where a reordered sum
may leave a 1e-16-relative residue of the larger terms), everything else (shapes, integers,
strings, booleans, NaN positions) exactly.

Regenerate only when a change is *meant* to change results (say so in the commit message, with the
effect), from the repository root::

    .venv/bin/python tests/golden/make_golden.py            # analytic cases + Sionna runs on the stored paths
    .venv/bin/python tests/golden/make_golden.py --retrace  # also re-trace the Sionna paths (needs sionna-rt, ~40 s)
"""
from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

HERE = Path(__file__).resolve().parent
RTOL = 1e-9
ATOL = 1e-12

SIONNA_TRACE_RTOL = 1e-6
SIONNA_TRACE_ATOL = {**{k: 1e-4 for k in ("toa_m", "delay_spread_m", "bounce_x", "bounce_y", "bounce_z", "lm_x",
                                          "lm_y", "lm_z", "tx_x", "tx_y", "tx_z")},
                     **{k: 1e-6 for k in ("aod_az", "aod_el", "aoa_az", "aoa_el")},
                     "doppler_hz": 1e-3, "power_db": 1e-4}
"""A re-trace against the stored Sionna paths: Sionna RT computes in float32 (Dr.Jit's LLVM backend, compiled for the
host CPU), so a re-trace on another machine or build may differ by a few float32 ulps (1.2e-7 relative each) and
the statistics over rays (delay spread, Doppler) by more. Floats agree to 1e-6 relative plus these floors, in each
column's unit (m, rad, Hz, dB); everything else (row count, labels, integer columns) exactly. The vehicles' true
states (float64, from the scenario, not the tracer) and the filter runs on the stored paths keep :data:`RTOL`."""

RETRACE_RUN_RTOL, RETRACE_RUN_ATOL = 1e-3, 1e-6
"""The filter run on a re-trace that differs from the stored one by float32 ulps, against the stored run: shapes,
labels and integers exactly, floats to 1e-3 relative plus 1e-6 in their own unit (measured: 2.2e-4 relative on a
re-trace that differed). A trace that is the same bit for bit must give the stored run at :data:`RTOL`."""

ANALYTIC_STEPS = 20  # fusion from k = 5 (vehicle 1) and 6 (vehicle 2), every 2 steps: 15 uploads
SIONNA_STEPS = 7     # k = 0..6: one upload of each vehicle
CITY_STEPS = 16      # canyon k = 0..15: uploads from k = 5, 6, 7 (cars a, b, c), every 2 steps; 21 VA, 19 VS paths

CASES: dict[str, dict[str, Any]] = {
    "odometry_p30": dict(variant="odometry", particles=30, seed=0),
    "baseline_p30": dict(variant="baseline", particles=30, seed=0),
    "cm1_p40": dict(variant="cm1", particles=40, seed=1),
    "proposed_p50": dict(variant="proposed", particles=50, seed=2),
    "proposed_p30_link_beta_labels": dict(
        variant="proposed", particles=30, seed=3,
        overrides=("sensor.model=\"link\"", "filter.pd_model=\"beta\"", "fusion.average_by_label=true")),
    "cm1_p30_gate_mergeva": dict(
        variant="cm1", particles=30, seed=4,
        overrides=("fusion.vs_reduction=\"gate\"", "filter.merge_va=4")),
}
"""Analytic cases: name -> run arguments (variant, particles, seed, scenario overrides)."""

SIONNA_CASES: dict[str, dict[str, Any]] = {
    v: dict(variant=v, particles=30, seed=0) for v in ("baseline", "cm1", "proposed")}
"""Runs on the stored Sionna paths: name -> run arguments."""

CITY_CASES: dict[str, dict[str, Any]] = {
    "proposed_p30": dict(variant="proposed", particles=30, seed=0, source="sionna"),
    "baseline_p30": dict(variant="baseline", particles=30, seed=1, source="sionna")}
"""Runs on the stored ``canyon`` paths with the defaults (no filter table): name -> run arguments (``source``: the
paths' origin, which picks the VS body model as a cache's would)."""


def paper():
    """The ``paper`` scenario."""
    from mmslam.scenes.scenario import load_preset

    return load_preset("paper")


def canyon():
    """The ``canyon`` preset: a city scene with no filter or fusion table, so its runs take the defaults."""
    from mmslam.scenes.scenario import load_preset

    return load_preset("canyon")


def analytic_inputs(scn, steps: int = ANALYTIC_STEPS) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """True states ``(steps, n_veh, 7)`` and the closed-form ``paths`` table of the first ``steps`` steps."""
    from mmslam.raytrace.analytic import AnalyticSource
    from mmslam.scenes.trajectory import true_trajectories

    states = true_trajectories(scn)[:steps]
    src = AnalyticSource(scn)
    parts = [src.trace_step(k, states[k]) for k in range(steps)]
    return states, {c: np.concatenate([p[c] for p in parts]) for c in parts[0]}


def sionna_trace(scn, steps: int = SIONNA_STEPS) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Trace ``steps`` steps of ``scn`` with Sionna RT into a temporary cache (the ``mmslam trace``
    path) and load it back: ``(states, paths)``."""
    from mmslam.raytrace.cache import load_cache
    from mmslam.raytrace.sionna_adapter import SionnaSource
    from mmslam.raytrace.trace import trace_scenario

    with tempfile.TemporaryDirectory(prefix="mmslam-golden-") as tmp:
        src = SionnaSource(scn, max_depth=1, samples_per_src=10**6, seed=0, scene_dir=Path(tmp) / "scene")
        cache = load_cache(trace_scenario(scn, src, Path(tmp) / "cache", steps=steps, progress=False))
        return np.asarray(cache.states, float), {k: np.asarray(v) for k, v in cache.paths.items()}


def save_paths(path: Path, states: np.ndarray, paths: dict[str, np.ndarray]) -> None:
    """Store a trace (strings as fixed-width unicode so no pickling is needed)."""
    arrs = {"states": states}
    for k, v in paths.items():
        arrs[f"paths/{k}"] = v.astype(str) if v.dtype == object else v
    np.savez_compressed(path, **arrs)


def load_paths(path: Path) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Inverse of :func:`save_paths` (string columns back to object arrays, as a cache gives them)."""
    with np.load(path) as f:
        states = f["states"]
        paths = {k[len("paths/"):]: (f[k].astype(object) if f[k].dtype.kind == "U" else f[k])
                 for k in f.files if k.startswith("paths/")}
    return states, paths


def _triu(a: np.ndarray) -> np.ndarray:
    i, j = np.triu_indices(a.shape[-1])
    return a[..., i, j]


def snapshot(scn, states: np.ndarray, paths: dict[str, np.ndarray], variant: str, particles: int,
             seed: int, overrides: tuple[str, ...] = (), steps: int | None = None,
             source: str | None = None) -> dict[str, np.ndarray]:
    """Run one case step by step; every array it should reproduce, flat (see the module docstring). ``source``: the
    paths' origin as a cache names it (``sionna``), passed to the run (None: unknown, as for the paper cases)."""
    from mmslam.scenes.scenario import with_overrides
    from mmslam.slam.filter import CooperativeRun  # the public facade (the same before and after issue 21)

    scn = with_overrides(scn, list(overrides))
    run = CooperativeRun(scn, states, paths, variant, particles, seed, steps, source=source)
    est_mean, est_cov, ess, resampled = [], [], [], []
    fused: dict[str, dict[str, list[np.ndarray]]] = {}
    for k in range(run.steps):
        ests = run.step(k)
        est_mean.append([e.mean for e in ests])
        est_cov.append([_triu(e.cov) for e in ests])
        ess.append([e.ess for e in ests])
        resampled.append([e.resampled for e in ests])
        if run.center is None:
            continue
        for code, gm in run.center.maps.items():
            name = run.center.specs[code].name
            d = fused.setdefault(name, {})
            live = np.asarray(gm.mask, bool)
            d.setdefault("step", []).append(np.full(int(live.sum()), k, np.int32))
            d.setdefault("w", []).append(gm.w[live])
            d.setdefault("m", []).append(gm.m[live])
            d.setdefault("P", []).append(_triu(gm.P[live]))
            if gm.pd_beta is not None:
                d.setdefault("pd_beta", []).append(gm.pd_beta[live])
            if gm.label is not None:
                d.setdefault("label", []).append(gm.label[live])
    res = run.result()
    out: dict[str, np.ndarray] = {
        "est/mean": np.asarray(est_mean, float), "est/cov_triu": np.asarray(est_cov, float),
        "est/ess": np.asarray(ess, float), "est/resampled": np.asarray(resampled, bool)}
    for name, d in fused.items():
        for key, parts in d.items():
            out[f"fused/{name}/{key}"] = np.concatenate(parts)
    for table in ("vehicles", "metrics", "landmarks"):
        for col, v in getattr(res, table).items():
            v = np.asarray(v)
            out[f"res/{table}/{col}"] = v.astype(str) if v.dtype == object else v
    return out


def compare(got: dict[str, np.ndarray], want: dict[str, np.ndarray], rtol: float = RTOL,
            atol: float | dict[str, float] = ATOL) -> list[str]:
    """Differences between two snapshots, one line each (empty: equal within the tolerances).

    ``atol``: one absolute floor for every float array, or one per key (in the key's own unit; a key not given
    gets :data:`ATOL`)."""
    bad = []
    for key in sorted(set(got) | set(want)):
        if key not in got or key not in want:
            bad.append(f"{key}: only in {'the fixture' if key in want else 'this run'}")
            continue
        g, w = np.asarray(got[key]), np.asarray(want[key])
        if g.shape != w.shape:
            bad.append(f"{key}: shape {g.shape}, fixture {w.shape}")
        elif g.dtype.kind == "f" and w.dtype.kind == "f" and g.dtype != w.dtype:
            bad.append(f"{key}: dtype {g.dtype}, fixture {w.dtype}")
        elif w.dtype.kind == "f":
            nan = np.isnan(w)
            if not np.array_equal(nan, np.isnan(g)):
                bad.append(f"{key}: NaN at other places")
                continue
            err = np.abs(g[~nan] - w[~nan])
            lim = rtol * np.abs(w[~nan]) + (atol.get(key, ATOL) if isinstance(atol, dict) else atol)
            if np.any(err > lim):
                i = int(np.argmax(err - lim))
                bad.append(f"{key}: {int(np.sum(err > lim))} of {w.size} differ; worst {g[~nan][i]!r} vs "
                           f"{w[~nan][i]!r}")
        elif not np.array_equal(g, w):
            bad.append(f"{key}: {int(np.sum(g != w))} of {w.size} differ")
    return bad


def load(path: Path) -> dict[str, np.ndarray]:
    with np.load(path) as f:
        return {k: f[k] for k in f.files}


def write(path: Path, arrays: dict[str, np.ndarray]) -> None:
    """Store a snapshot, unless the stored one already equals it within :func:`compare`'s tolerances (then the file
    is left as it is, so a regeneration rewrites only the fixtures a change moved)."""
    if path.exists() and not compare(arrays, load(path)):
        print(f"{path.name}: unchanged")
        return
    np.savez_compressed(path, **arrays)
    print(path.name)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--retrace", action="store_true", help="re-trace the Sionna paths (sionna-rt, ~20 s)")
    args = ap.parse_args(argv)
    scn = paper()
    states, paths = analytic_inputs(scn)
    for name, case in CASES.items():
        write(HERE / f"analytic_{name}.npz", snapshot(scn, states, paths, **case))
    sp = HERE / "sionna_paths.npz"
    if args.retrace or not sp.exists():
        save_paths(sp, *sionna_trace(scn))
        print(sp.name)
    s_states, s_paths = load_paths(sp)
    for name, case in SIONNA_CASES.items():
        write(HERE / f"sionna_{name}.npz", snapshot(scn, s_states, s_paths, **case))
    cp = HERE / "city_paths.npz"
    city = canyon()
    if args.retrace or not cp.exists():
        save_paths(cp, *sionna_trace(city, CITY_STEPS))
        print(cp.name)
    c_states, c_paths = load_paths(cp)
    for name, case in CITY_CASES.items():
        write(HERE / f"city_{name}.npz", snapshot(city, c_states, c_paths, **case))
    return 0


if __name__ == "__main__":
    sys.exit(main())
