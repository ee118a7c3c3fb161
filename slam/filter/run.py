"""The cooperative run loop: measurements -> per-vehicle local filters -> fusion at the BS -> Result.

:class:`CooperativeRun` is the public step API; one step ``k`` (:meth:`CooperativeRun.step`) is:

1. ``predict_at_bs(k)``: the fusion centre predicts its maps (variants with ``predict_at_bs``);
2. per vehicle ``n``: ``local_step(k, n)`` (the vehicle's :meth:`LocalFilter.step` on its
   measurement set with the known speed / turn rate of step ``k-1``), ``record_vehicle`` (state
   errors, GOSPA of its averaged maps), ``upload(k, n, est)`` (if ``k`` is one of the vehicle's
   fusion steps: fuse its averaged maps at the BS and overwrite its particles' maps with the
   fused ones);
3. ``record_fused(k)``: GOSPA of the BS maps.

Prior (per Monte Carlo run): the filter's initial estimate is drawn once from
``N(s_0, diag(prior_std^2))`` around the true initial state ``s_0`` (the paper: "the initial
prior of the vehicle state is sampled from N(s_0; s_0^n, S_0^n)"), and the particles from
``N(initial estimate, diag(prior_std^2))``. Dead reckoning (a variant without
``measurement_update``, the ``odometry`` reference) is the same filter without correction,
births or fusion.

Random streams: ``SeedSequence(seed)`` spawns independent streams for the measurement
simulation, the prior draws, and each vehicle's filter, so all variants of one seed see the
same measurements and the same prior.
"""
from __future__ import annotations

import time
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from mmslam.errors import MmslamError
from mmslam.scenes.scenario import Scenario, with_overrides

from ..models.dynamics import wrap_angle
from ..eval.evaluation import LM_DT, MET_DT, MapScorer, Table
from .fusion_center import FusionCenter, ego_gaussian, filter_detect_probs
from .process_noise import truth_has_process_noise, vehicle_process_std  # noqa: F401  (public here too)
from ..specs.landmarks import check_type_rows, known_codes, landmark_types
from .known_map import KnownMap
from .local_filter import LocalFilter, StepEstimate
from ..core.memory import retain_freed_memory
from .rbpf import position_nees
from .result import Result
from ..specs.variants import DEFAULT_VARIANT, VariantSpec, get_variant

VEH_DT = {"step": np.int32, "vehicle": np.int16, "x": float, "y": float, "z": float, "heading": float,
          "bias": float, "true_x": float, "true_y": float, "true_z": float, "true_heading": float,
          "true_bias": float, "pos_err": float, "pos_nees": float, "heading_err": float, "bias_err": float}


POINT_VS_SOURCES = ("analytic",)
"""Path sources whose VS paths bounce at the car's antenna point (closed-form point scatterers): under
``filter.vs_body_model = "auto"`` their runs use the point VS; every other (a ray tracer on car meshes) the
ellipsoid body."""


def resolve_vs_body(scn: Scenario, source: str | None) -> tuple[Scenario, str]:
    """``filter.vs_body_model = "auto"`` made explicit for a run on paths of ``source`` (a cache's
    ``source``; None: paths of unknown origin, the point model): ``ellipsoid`` on a traced source (its cars are
    meshes), ``point`` on :data:`POINT_VS_SOURCES`. Returns the scenario and the model used, with the reason
    (``Result.meta['vs_body_model']``)."""
    import dataclasses

    model = scn.filter.vs_body_model
    if model != "auto":
        return scn, model
    model = "point" if source is None or source in POINT_VS_SOURCES else "ellipsoid"
    why = ("paths of unknown source" if source is None else
           f"{source} source: {'point scatterers' if model == 'point' else 'car meshes'}")
    return dataclasses.replace(scn, filter=dataclasses.replace(scn.filter, vs_body_model=model)), f"{model} (auto: {why})"


def link_detect_rate(scn: Scenario, states: np.ndarray, paths: dict[str, np.ndarray], code: int) -> tuple[float, int]:
    """The link budget's mean detection probability of the type-``code`` paths inside the FOV.

    Each row of ``paths`` of that type whose landmark lies within ``sensor.fov_range`` of the vehicle's antenna
    (``states (steps, n_veh, 7)``, m; only range-gated types, the others count at any range) gets
    ``p_D = Q_1(sqrt(2 SNR), sqrt(-2 ln pfa))`` at its traced power (:meth:`~mmslam.slam.sim.sensor.LinkBudget.detect_prob`); returns
    their mean and their number (``(nan, 0)`` without such a row). A prediction from the paths' power and the
    sensor's hardware, not a count of detections.
    """
    from ..sim.sensor import LinkBudget, fov_detect_prob

    sel = np.flatnonzero(np.asarray(paths["type"]) == code)
    step, rx = np.asarray(paths["step"])[sel], np.asarray(paths["rx"])[sel]
    keep = step < states.shape[0]
    sel, step, rx = sel[keep], step[keep], rx[keep]
    if sel.size:  # the sensor's FOV rule (fov_detect_prob: range-gated types within fov_range)
        lm = np.stack([np.asarray(paths[c], float)[sel] for c in ("lm_x", "lm_y", "lm_z")], -1)
        sel = sel[fov_detect_prob(np.asarray(states, float)[step, rx, 0:3], lm, code, scn.sensor, p_inside=1.0) > 0]
    if sel.size == 0:
        return float("nan"), 0
    link = LinkBudget.from_sensor(scn.sensor)
    pd = link.detect_prob(link.snr_db(np.asarray(paths["power_db"], float)[sel]))
    return float(np.mean(pd)), int(sel.size)


def resolve_detect_probs(scn: Scenario, states: np.ndarray, paths: dict[str, np.ndarray]
                         ) -> tuple[Scenario, dict[str, dict[str, float]]]:
    """Each type with ``filter.types.<T>.p_detect_source = "link"`` under a power-aware sensor model (``link``,
    ``estimated``) gets ``p_detect`` = :func:`link_detect_rate` on ``paths`` (clipped to
    [0.01, 0.99]; kept where the type has no path in the FOV). Returns the scenario and, per changed type,
    ``{"p_detect", "paths"}`` (``Result.meta['p_detect_from_link']``). The constant model: unchanged."""
    import dataclasses

    if scn.sensor.model not in ("link", "estimated"):
        return scn, {}
    types, notes = dict(scn.filter.types), {}
    for spec in landmark_types():
        tp = scn.filter.type_params(spec.name)
        if tp.p_detect_source != "link":
            continue
        rate, n = link_detect_rate(scn, states, paths, spec.code)
        if n == 0:
            continue
        pd = float(np.clip(rate, 0.01, 0.99))
        types[spec.name] = dataclasses.replace(tp, p_detect=pd)
        notes[spec.name] = {"p_detect": pd, "paths": n}
    if not notes:
        return scn, {}
    return dataclasses.replace(scn, filter=dataclasses.replace(scn.filter, types=types)), notes


def schedule(scn: Scenario, n_veh: int, steps: int) -> list[set[int]]:
    """Per vehicle, the steps at which it uploads to the BS: ``fusion.start[n] + i fusion.period``
    (one ``start`` for all vehicles if ``fusion.start`` has a single entry)."""
    fu = scn.fusion
    starts = fu.start if len(fu.start) == n_veh else tuple(fu.start[0] for _ in range(n_veh))
    return [set(range(int(s), steps, int(fu.period))) for s in starts]


def resolve_particles(scn: Scenario, particles: int | None) -> int:
    """``particles``, or the scenario's ``filter.particles`` when None; an integer >= 1.

    Raises:
        MmslamError: not an integer >= 1.
    """
    return check_particles(scn.filter.particles if particles is None else particles)


def check_particles(particles: Any) -> int:
    """``particles`` as an int; raises MmslamError unless it is an integer >= 1."""
    if isinstance(particles, bool) or not isinstance(particles, (int, np.integer)) or particles < 1:
        raise MmslamError(f"particles={particles!r}: expected an integer >= 1")
    return int(particles)


def all_types() -> tuple[int, ...]:
    """Codes of every registered landmark type (the default ``include_types``)."""
    return tuple(s.code for s in landmark_types())


class CooperativeRun:
    """One Monte Carlo run of cooperative MM-PHD-SLAM, stage by stage (see the module docstring).

    Args:
        scn: scenario (sensor, filter, fusion, evaluation parameters).
        states: ``(steps, n_veh, 7)`` true vehicle states (cache ``states``).
        paths: ``paths`` table columns for (at least) these steps.
        variant: a :class:`~mmslam.slam.specs.variants.VariantSpec` or a registered name.
        particles: particles per vehicle (None: ``filter.particles``).
        seed: Monte Carlo seed (measurement noise, clutter, detections, prior, filter draws).
        steps: number of steps to run (default all of ``states``).
        include_types: path type codes turned into measurements (default all registered types).
        measurement_update: False forces dead reckoning (also implied by the variant).
        evaluate: keep the truth and the per-step tables (False: the filters only, e.g. benchmarks).
        known_map: an oracle map of one type given to every vehicle at every step
            (:mod:`mmslam.slam.filter.known_map`, experiments only); None: every map is estimated.

    Attributes:
        filters: the vehicles' :class:`LocalFilter`; ``center``: the :class:`FusionCenter` (None
        without measurement update); ``meas``: the simulated measurements; ``true``: ``(steps,
        n_veh, 7)`` true states (with the simulated clock bias); ``schedule``: upload steps per vehicle.
    """

    def __init__(self, scn: Scenario, states: np.ndarray, paths: dict[str, np.ndarray],
                 variant: str | VariantSpec = DEFAULT_VARIANT, particles: int | None = None, seed: int = 0,
                 steps: int | None = None, include_types: Sequence[int] | None = None, *,
                 measurement_update: bool = True, evaluate: bool = True, rays: dict[str, np.ndarray] | None = None,
                 estimates_dir: str | Path | None = None, source: str | None = None,
                 known_map: KnownMap | None = None) -> None:
        from ..sim.sensor import fov_detect_prob, odometry_readings, simulate_measurements

        self.t0 = time.perf_counter()
        check_type_rows(scn)
        scn, self.vs_body_model = resolve_vs_body(scn, source)
        retain_freed_memory()  # no page faults per step for the maps' arrays (slam/core/memory.py)
        self.variant = get_variant(variant)
        self.measurement_update = bool(measurement_update and self.variant.measurement_update)
        self.particles = resolve_particles(scn, particles)
        include_types = all_types() if include_types is None else tuple(include_types)
        states = np.asarray(states, float)
        if states.ndim != 3 or states.shape[-1] != 7 or states.shape[0] < 1:
            raise MmslamError(f"states shape {states.shape}: expected (steps >= 1, n_vehicles, 7)")
        n_avail, n_veh = states.shape[0], states.shape[1]
        if n_veh != len(scn.vehicles):
            raise MmslamError(f"states have {n_veh} vehicles but scenario '{scn.name}' has {len(scn.vehicles)}")
        if steps is None:
            steps = n_avail
        if isinstance(steps, bool) or not isinstance(steps, (int, np.integer)) or not 1 <= steps <= n_avail:
            raise MmslamError(f"steps={steps!r}: expected an integer in 1..{n_avail} (the cached steps)")
        codes = known_codes()
        bad = [t for t in include_types if t not in codes]
        if bad:
            names = ", ".join(f"{s.code} {s.name}" for s in landmark_types())
            raise MmslamError(f"include_types {list(include_types)}: unknown type codes {bad}; use {names}, 4 OTHER")
        self.scn, self.seed, self.steps, self.n_veh = scn, int(seed), int(steps), n_veh
        self.include_types = include_types
        states = states[:steps]
        step_col = np.asarray(paths["step"])
        sub = {k: np.asarray(v)[step_col < steps] for k, v in paths.items()}
        # the p_D of types that take it from the sensor's link budget (filter.types.<T>.p_detect_source)
        scn, self.p_detect_from_link = resolve_detect_probs(scn, states, sub)
        self.scn = scn

        # ---- stage 0: measurements of the whole run, prior, filters
        ss = np.random.SeedSequence(int(seed))
        s_meas, s_prior, *s_veh, s_odo = ss.spawn(3 + n_veh)  # children by index: the first 2 + n_veh as before
        self.estimator_counts = None
        if scn.sensor.model == "estimated":  # measurements from the channel estimator (estimated_sensor.py)
            from ..sim.estimated_sensor import estimated_run, resolve_estimates, to_measurements

            if rays is None:
                raise MmslamError("sensor.model = \"estimated\" needs the traced rays: run it on a cache "
                                  "(mmslam run / ablate), not on paths alone")
            est = estimated_run(scn, states, {k: np.asarray(v)[np.asarray(rays["step"]) < steps] for k, v in rays.items()},
                                sub, np.random.default_rng(s_meas), estimates_dir, int(seed))
            est = resolve_estimates(scn, est, steps, n_veh, sub)  # non-maximum suppression (sensor.est_resolve)
            self.meas = to_measurements(scn, est, steps, n_veh)
            self.estimator_counts = est["counts"]
        else:
            self.meas = simulate_measurements(scn, states, sub, np.random.default_rng(s_meas),
                                              include_types=include_types)
        self.true = np.asarray(self.meas.true_states, float)
        odo_std = np.asarray(scn.sensor.odometry_noise_std, float)
        self.odometry = (odometry_readings(self.true, odo_std, np.random.default_rng(s_odo)) if (odo_std > 0).any()
                         else None)
        """``(steps, n_veh, 2)`` the speed and turn rate the filters read (``sensor.odometry_noise_std``), None: exact"""
        R = scn.filter.r_scale * np.asarray(self.meas.R, float)
        sensor = scn.sensor
        pd_type = filter_detect_probs(scn)

        # the sensor's FOV (where its p_detect > 0) with the filter's per-type probability inside
        pd_inside = {t: float(p) if sensor.p_detect > 0 else 0.0 for t, p in pd_type.items()}

        def pd_fn(u: np.ndarray, x: np.ndarray, t: int) -> np.ndarray:
            """The filter's p_D: its per-type probability inside the FOV (sensor's range gate), 0 outside."""
            return fov_detect_prob(u, x, t, sensor, p_inside=pd_inside[int(t)])

        self.pd_fn = pd_fn
        prior_rng = np.random.default_rng(s_prior)
        prior_std = np.asarray(scn.filter.prior_std, float)
        self.process_std = vehicle_process_std(scn)
        """``(n_veh, 7)`` each vehicle's process noise std (filter.height_process)"""
        self.filters: list[LocalFilter] = []
        for n in range(n_veh):
            prior_mean = self.true[0, n] + prior_rng.standard_normal(7) * prior_std
            self.filters.append(LocalFilter(scn, self.variant, self.particles, prior_mean, R,
                                            float(self.meas.clutter_intensity), pd_fn,
                                            np.random.default_rng(s_veh[n]), self.measurement_update, vehicle=n,
                                            known_map=known_map, process_std=self.process_std[n]))
        self.center = FusionCenter(scn, self.variant) if self.measurement_update else None
        self.schedule = schedule(scn, n_veh, self.steps)
        self._acc_fov: list[list[np.ndarray]] = [[] for _ in range(n_veh)]
        self.scorer = MapScorer(scn, sub, self.true[:steps], list(scn.vehicle_names)) if evaluate else None
        self.vehicle_rows = Table()

    # ------------------------------------------------------------------ stages
    def predict_at_bs(self, k: int) -> None:
        """Stage 1 of step ``k > 0``: the fusion centre's prediction (no-op at ``k = 0`` or without fusion)."""
        if self.center is not None and k > 0:
            self.center.predict()

    def local_inputs(self, k: int, n: int) -> tuple[np.ndarray, float | None, float | None, np.ndarray | None]:
        """Vehicle ``n``'s measurement set ``Z (J, 5)`` at step ``k``, the known speed (m/s) and turn
        rate (rad/s) of step ``k-1`` (its odometry reading under ``sensor.odometry_noise_std``; None at ``k = 0``) and the per-measurement covariances
        ``R_z (J, 5, 5)`` of the power-aware sensor (scaled like ``R``; None for the constant model)."""
        meas, scn = self.meas, self.scn
        sel = np.asarray(meas.mask[k, n], bool)
        Z = np.asarray(meas.z[k, n], float)[sel]
        inputs = self.true[..., 4:6] if self.odometry is None else self.odometry
        spd, tr = (float(inputs[k - 1, n, 0]), float(inputs[k - 1, n, 1])) if k > 0 else (None, None)
        # the constant sensor model's per-measurement covariances are all R: the filter's shared R
        # (one batched correction) instead of J equal copies (a per-measurement loop, ~2.5x slower)
        R_z = (None if meas.R_meas is None or scn.sensor.model == "constant" else
               scn.filter.r_scale * np.einsum("ja,ab->jab", np.asarray(meas.R_meas[k, n], float)[sel], np.eye(5)))
        return Z, spd, tr, R_z

    def local_step(self, k: int, n: int) -> StepEstimate:
        """Stage 2a: vehicle ``n``'s local filter step ``k`` (:meth:`LocalFilter.step`)."""
        Z, spd, tr, R_z = self.local_inputs(k, n)
        return self.filters[n].step(Z, spd, tr, R_z)

    def record_vehicle(self, k: int, n: int, est: StepEstimate) -> None:
        """Stage 2b: state errors of vehicle ``n`` and GOSPA of its averaged maps at step ``k``."""
        ts = self.true[k, n]
        self.vehicle_rows.add(step=k, vehicle=n, x=est.mean[0], y=est.mean[1], z=est.mean[2], heading=est.mean[3],
                              bias=est.mean[6], true_x=ts[0], true_y=ts[1], true_z=ts[2], true_heading=ts[3],
                              true_bias=ts[6], pos_err=float(np.linalg.norm(est.mean[0:3] - ts[0:3])),
                              pos_nees=position_nees(est.mean[0:2] - ts[0:2], est.cov[0:2, 0:2]),
                              heading_err=float(wrap_angle(est.mean[3] - ts[3])), bias_err=float(est.mean[6] - ts[6]))
        if self.scorer is not None:
            self.scorer.record(k, self.scn.vehicle_names[n], est.avg_maps, self.scorer.vehicle_truth(k, n), n)

    def upload(self, k: int, n: int, est: StepEstimate) -> bool:
        """Stage 2c: if ``k`` is a fusion step of vehicle ``n``, fuse its averaged maps at the BS
        (accumulated FOV since its last upload) and downlink the fused maps; returns whether it did."""
        self._acc_fov[n].append(est.mean[0:3])
        if self.center is None or k not in self.schedule[n]:
            return False
        fused = self.center.fuse(est.avg_maps, np.array(self._acc_fov[n]), est.mean, est.cov, vehicle=n,
                                 unconfirmed=self.filters[n].unconfirmed)
        self.filters[n].downlink(fused, ego_gaussian(est.mean, est.cov, self.scn.filter.vs_process_std))
        if self.scorer is not None:  # its maps now hold the fused map: so does their truth
            self.scorer.record_downlink(n, k)
        self._acc_fov[n] = []
        return True

    def record_fused(self, k: int) -> None:
        """Stage 3: GOSPA of the BS maps at step ``k`` (empty maps without fusion)."""
        if self.scorer is not None:
            maps = self.center.maps if self.center is not None else {}
            self.scorer.record(k, "fused", maps, self.scorer.fused_truth(k), self.n_veh)
            self.scorer.record_others(k, maps)

    def step(self, k: int) -> list[StepEstimate]:
        """All stages of step ``k``; returns the vehicles' estimates."""
        self.predict_at_bs(k)
        out = []
        for n in range(self.n_veh):
            est = self.local_step(k, n)
            self.record_vehicle(k, n, est)
            self.upload(k, n, est)
            out.append(est)
        self.record_fused(k)
        return out

    def run(self, meta: dict[str, Any] | None = None) -> Result:
        """Every step, then :meth:`result` (``meta``: extra ``Result.meta`` entries)."""
        for k in range(self.steps):
            self.step(k)
        return self.result(meta)

    def result(self, meta: dict[str, Any] | None = None) -> Result:
        """The :class:`~mmslam.slam.filter.result.Result` of the steps run so far (``meta``: extra entries)."""
        from mmslam import __version__ as mm_version  # noqa: PLC0415

        scn = self.scn
        md: dict[str, Any] = {"variant": self.variant.name, "particles": self.particles, "seed": self.seed,
                              "scenario": scn.name, "cache": None, "source": None, "steps": self.steps,
                              "vehicle_names": list(scn.vehicle_names),
                              "include_types": [int(t) for t in self.include_types],
                              "measurement_update": self.measurement_update,
                              "fusion_start": int(min(scn.fusion.start)), "vs_body_model": self.vs_body_model,
                              "p_detect_from_link": self.p_detect_from_link,
                              "height_process_std": self.process_std[:, 2].tolist(),
                              "adaptive_birth": bool(self.filters and self.filters[0].adaptive_birth),
                              "process_std": self.process_std.tolist(),
                              "exact_truth": [not truth_has_process_noise(scn, n) for n in range(len(scn.vehicles))],
                              "wall_time_s": time.perf_counter() - self.t0, "mmslam_version": mm_version,
                              "gospa": {"c": float(scn.evaluation.gospa_c), "p": float(scn.evaluation.gospa_p),
                                        "alpha": float(scn.evaluation.gospa_alpha)}}
        cols, counts = self.meas.origin_counts()  # evaluation labels of the measurements (never used by the filter)
        md["measurement_counts"] = {"model": scn.sensor.model, "columns": cols,
                                    "per_step_vehicle": counts[:self.steps].tolist()}
        if self.estimator_counts is not None:  # evaluation labels of the estimates (never used by the filter)
            from ..sim.estimated_sensor import RESOLVED_COLUMNS

            md["estimator_counts"] = {"columns": list(RESOLVED_COLUMNS),
                                      "per_step_vehicle": np.asarray(self.estimator_counts)[:self.steps].tolist()}
        md.update(meta or {})
        md["wall_time_s"] = time.perf_counter() - self.t0
        mt = self.scorer.metrics if self.scorer is not None else Table()
        lt = self.scorer.landmarks if self.scorer is not None else Table()
        return Result(self.vehicle_rows.arrays(VEH_DT), mt.arrays(MET_DT), lt.arrays(LM_DT), md)


def run_filter(scn: Scenario, states: np.ndarray, paths: dict[str, np.ndarray],
               variant: str | VariantSpec = DEFAULT_VARIANT, particles: int | None = None, seed: int = 0,
               steps: int | None = None, include_types: Sequence[int] | None = None,
               meta: dict[str, Any] | None = None, *, measurement_update: bool = True,
               rays: dict[str, np.ndarray] | None = None, estimates_dir: str | Path | None = None,
               source: str | None = None, known_map: KnownMap | None = None) -> Result:
    """Run cooperative MM-PHD-SLAM on noise-free paths (no cache needed): :meth:`CooperativeRun.run`.

    Args:
        scn: scenario (sensor, filter, fusion, evaluation parameters).
        states: ``(steps, n_veh, 7)`` true vehicle states (cache ``states``).
        paths: ``paths`` table columns for (at least) these steps.
        variant: a registered variant (``baseline`` | ``cm1`` | ``proposed``, or the reference
            ``odometry``: dead reckoning with the same prior and inputs) or a VariantSpec; default
            :data:`~mmslam.slam.specs.variants.DEFAULT_VARIANT` (``proposed``).
        particles: particles per vehicle (>= 1; None: the scenario's ``filter.particles``).
        seed: Monte Carlo seed (measurement noise, clutter, detections, prior, filter draws).
        steps: number of steps to run (default all of ``states``).
        include_types: path types turned into measurements (e.g. ``(0, 1, 2)`` drops VS rows;
            default every registered type).
        meta: extra entries for ``Result.meta`` (e.g. the cache hash).
        measurement_update: False runs dead reckoning (prediction only).
        rays, estimates_dir: the ``rays`` table and where to cache the estimates (``sensor.model =
            "estimated"`` only, :mod:`mmslam.slam.sim.estimated_sensor`).
        source: the path source (a cache's ``source``: ``sionna``, ``analytic``); decides
            ``filter.vs_body_model = "auto"`` (:func:`resolve_vs_body`; None: the point VS).
        known_map: an oracle map of one type (:mod:`mmslam.slam.filter.known_map`; experiments only).

    Returns:
        A :class:`~mmslam.slam.filter.result.Result` (tables documented in :mod:`mmslam.slam.filter.result`).
    """
    return CooperativeRun(scn, states, paths, variant, particles, seed, steps, include_types,
                          measurement_update=measurement_update, rays=rays, estimates_dir=estimates_dir,
                          source=source, known_map=known_map).run(meta)


def run_slam(cache_dir: str | Path, variant: str | VariantSpec = DEFAULT_VARIANT, particles: int | None = None,
             seed: int = 0, steps: int | None = None, include_types: Sequence[int] | None = None,
             overrides: Sequence[str] = (), compile_notice: Callable[[str], None] | None = None,
             known_map: KnownMap | None = None) -> Result:
    """Load a path cache and run :func:`run_filter` on it.

    The variant's numba kernels are compiled (in parallel processes, if not cached yet: a fresh
    install; ``compile_notice`` gets a one-line message first) and loaded before the run starts, so
    ``meta['wall_time_s']`` never includes compilation (:func:`mmslam.slam.filter.precompile.ensure_compiled`).
    ``compile_notice`` also gets the cache's one-line notices: a trace that stopped early
    (:meth:`PathCache.partial_notice`), and its settings (:meth:`PathCache.settings_notice`: parameters its scenario
    left open follow this mmslam's defaults; ``meta['settings_from_defaults']`` lists them).

    ``overrides``: ``section.key=value`` strings (e.g. ``"fusion.vs_reduction=gate"``) applied to
    the cached scenario's [sensor], [filter], [fusion] and [evaluation] parameters
    (:func:`mmslam.scenes.scenario.with_overrides`); they change the filter run, never the trace.
    ``particles`` None: the (overridden) scenario's ``filter.particles``. ``known_map``: an oracle map of one
    type (:mod:`mmslam.slam.filter.known_map`, built from the cache's paths; experiments only).

    Raises:
        CacheError: the cache is missing, corrupt or of another schema (from ``load_cache``).
        MmslamError: ``particles < 1``, an unknown variant or a bad ``steps``.
    """
    get_variant(variant)
    if particles is not None:
        check_particles(particles)
    from mmslam.raytrace.cache import load_cache

    cache = load_cache(cache_dir)
    scn = with_overrides(cache.scenario, list(overrides))
    if scn.geometry_hash() != cache.scenario.geometry_hash():
        raise MmslamError(f"--set {', '.join(overrides)}: changes the traced scenario (the cache's truth); "
                          "trace a new cache with that scenario instead")
    meta = {"cache": cache.manifest.get("config_hash"), "source": cache.manifest.get("source"),
            "cache_path": str(cache.path), "overrides": list(overrides),
            "settings_from_defaults": list(cache.settings_changed)}
    for note in (cache.partial_notice(), cache.settings_notice()):
        if note and compile_notice is not None:
            compile_notice(note)
    from .precompile import ensure_compiled

    ensure_compiled([get_variant(variant).name], notice=compile_notice)
    if scn.sensor.model == "estimated":  # the estimator's kernels too, before the run's clock
        from ..sim.estimated_sensor import estimator_kernels_cached, warm_up_estimator

        if not estimator_kernels_cached() and compile_notice is not None:
            compile_notice("compiling the channel estimator's numba kernels once for this install (~20 s of CPU); "
                           "later runs load them")
        warm_up_estimator(scn.sensor, scn.frequency_hz)
    est = {"rays": cache.read_rays(), "estimates_dir": cache.path} if scn.sensor.model == "estimated" else {}
    res = run_filter(scn, cache.states, cache.paths, variant=variant, particles=particles,
                     seed=seed, steps=steps, include_types=include_types, meta=meta, source=meta["source"],
                     known_map=known_map, **est)
    if compile_notice is not None and res.meta.get("p_detect_from_link"):
        compile_notice("p_D from the link budget (filter.types.<T>.p_detect_source = link, sensor.model = "
                       f"{scn.sensor.model}): " + ", ".join(
                           f"{t} {v['p_detect']:.2f} (mean over {v['paths']} paths in the FOV)"
                           for t, v in res.meta["p_detect_from_link"].items()))
    exact = res.meta.get("exact_truth") or []
    if compile_notice is not None and any(exact):
        ps = np.asarray(res.meta["process_std"], float)[np.asarray(exact, bool)]
        compile_notice(f"process noise of the {int(np.sum(exact))} car(s) whose truth drives the motion model exactly: "
                       f"x, y {ps[:, 0].max():.3g} m, heading {ps[:, 3].max():.3g} rad per step (filter.motion_jitter_std "
                       "with the odometry's error; sensor.vehicle_noise_std only where sensor.true_process_noise "
                       "gives a ct car's truth that noise)")
    if (compile_notice is not None and scn.filter.adaptive_birth and res.meta.get("measurement_update")
            and not res.meta.get("adaptive_birth")):  # odometry births nothing: no notice
        compile_notice("filter.adaptive_birth: no clutter (sensor.clutter_mean = 0), so no share of a measurement is "
                       "unexplained; every measurement births at filter.birth_weight")
    hz = res.meta.get("height_process_std") or []
    if compile_notice is not None and any(h > scn.sensor.vehicle_noise_std[2] for h in hz):
        compile_notice("height process noise from the routes' slope (filter.height_process = route): " + ", ".join(
            f"{name} {h:.3g}" for name, h in zip(scn.vehicle_names, hz)) + " m per step")
    return res
