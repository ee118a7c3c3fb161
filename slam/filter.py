"""Cooperative MM-PHD-SLAM: per-vehicle RBPF with GM-PHD maps per type, map fusion at the BS.

Variants (DESIGN.md section 6):

- ``baseline`` (TWC2020): maps VA, SP (3-D points); the BS is a known fixed landmark; VS
  measurements are unmodelled (they feed VA/SP births or are explained as clutter); AA fusion
  ``F_AA`` of VA and SP maps.
- ``cm1``: adds the 7-D VS map ``[x, y, z, vx, vy, vz, xi]`` to the local filter (prediction
  with ``predict_vs``, birth, correction, its term in ``psi(z)`` and in the particle weight).
  Fusion of the VS map: the *baseline* operator ``F_AA`` on the uploaded averaged VS map, with
  no prediction at the BS and the accumulated FOV of radius ``fov_range`` (our choice where the
  paper leaves it open).
- ``proposed``: cm1 + the global countermeasure: the uploaded VS map is
  ``ego_vs_average(averaged VS map, ego posterior)``; the fused VS map is predicted at the BS
  every step (``predict_bs_vs``, no birth) and fused with ``fuse_vs``.

One local step (:meth:`LocalFilter.step`), for vehicle ``n`` at step ``k``:

1. prediction (``k > 0``): birth Gaussians from the previous step's measurements and particle
   states (:func:`mmslam.slam.birth.birth_gm`, weight ``birth_weight``); particles propagated by
   the CT model with the known speed / turn rate of step ``k-1`` and process noise
   ``sensor.vehicle_noise_std``; static maps times ``p_S``; VS map (with its births) through
   ``predict_vs`` (CT, process noise, dithering);
2. correction with ``Z_k`` (eqs. prevCorrPHD / propCorrPHD, CKF per Gaussian, filter noise
   ``R = r_scale R_true``); particle log-weights ``+= sum_z log psi(z)`` (product form, as the
   authors' code; the paper's eq. prevCorrComW writes a sum). Corrected components below the
   prune threshold are never materialised (they would be pruned in step 3 anyway);
3. reduction per type (``prune_merge``: prune, merge, cap, max_trace);
4. estimates with the corrected weights: weighted-mean state, averaged maps (``average_map``
   with ``fusion.average_prune``), landmark estimates = averaged-map components with weight
   ``>`` the type's threshold (each counted once; weights are *not* rounded to multiple targets);
5. systematic resampling when ``ESS < resample_ess P`` (no roughening: the process noise added
   at every prediction keeps the particles diverse).

Prior (per Monte Carlo run): the filter's initial estimate is drawn once from
``N(s_0, diag(prior_std^2))`` around the true initial state ``s_0`` (the paper: "the initial
prior of the vehicle state is sampled from N(s_0; s_0^n, S_0^n)"), and the particles from
``N(initial estimate, diag(prior_std^2))``. Dead reckoning (``measurement_update=False``) is the
same filter without correction, births or fusion.

Random streams: ``SeedSequence(seed)`` spawns independent streams for the measurement
simulation, the prior draws, and each vehicle's filter, so all variants of one seed see the
same measurements and the same prior.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from mmslam.errors import MmslamError
from mmslam.scenes.scenario import Scenario, with_overrides

from .birth import birth_from_moments, birth_moments_by_kind
from .dynamics import wrap_angle
from .gm import GM, concat, empty
from .gmphd import bs_logterm, check_phd_mass, corrected_gm, log_psi, predict_static, type_terms
from .measurement import BS, SP, TYPE_NAMES, VA, VS
from .rbpf import (ess, init_particles, normalise_log_weights, propagate, systematic_resample,
                   weighted_state_cov, weighted_state_mean)
from .reduction import average_map, merge_pairs, prune_merge
from .result import Result

VARIANTS = ("baseline", "cm1", "proposed")
REFERENCES = ("odometry",)
"""Reference runs beside the variants: ``odometry`` is dead reckoning from the prior with the known
speed and turn rate, no measurement update and empty maps (its map GOSPA is that of an empty map)."""
EVAL_TYPES = (VA, SP, VS)


def _dims(t: int) -> int:
    return 7 if t == VS else 3


def _check_variant(variant: str) -> None:
    if variant not in VARIANTS:
        raise MmslamError(f"unknown variant {variant!r}; expected one of {', '.join(VARIANTS)}")


def _broadcast_gm(g: GM, n: int) -> GM:
    """A single mixture (batch ``()``) copied to every one of ``n`` particles (batch ``(n,)``)."""
    return GM(np.repeat(g.w[None], n, 0), np.repeat(g.m[None], n, 0), np.repeat(g.P[None], n, 0),
              np.repeat(g.mask[None], n, 0))


def _take(g: GM, idx: np.ndarray) -> GM:
    return GM(g.w[idx], g.m[idx], g.P[idx], g.mask[idx])


@dataclass
class StepEstimate:
    """Estimates of one vehicle after one local step (before resampling).

    ``mean (7,)``, ``cov (7, 7)``: weighted particle mean / covariance of the vehicle state;
    ``avg_maps``: type -> averaged map (GM, batch ``()``); ``ess``: effective sample size
    before resampling; ``resampled``: whether resampling happened.
    """

    mean: np.ndarray
    cov: np.ndarray
    avg_maps: dict[int, GM]
    ess: float
    resampled: bool


class LocalFilter:
    """The RBPF of one vehicle: ``P`` particles, each with one GM-PHD map per landmark type.

    Args:
        scn: the scenario (sensor, filter and fusion parameters; BS position).
        variant: ``baseline`` | ``cm1`` | ``proposed``.
        particles: number of particles ``P``.
        prior_mean: ``(7,)`` the initial state estimate.
        R: ``(5, 5)`` the filter's measurement covariance (already scaled by ``r_scale``).
        clutter_intensity: ``c(z)`` (per unit of measurement-space volume).
        pd_fn: ``pd_fn(vehicle_pos (..., 3), lm_pos (..., 3), lm_type) -> (...)`` detection
            probability (typically :func:`mmslam.slam.sensor.fov_detect_prob`).
        rng: this filter's random generator.
        measurement_update: False for dead reckoning (no correction, births or map).
    """

    def __init__(self, scn: Scenario, variant: str, particles: int, prior_mean: np.ndarray,
                 R: np.ndarray, clutter_intensity: float,
                 pd_fn: Callable[[np.ndarray, np.ndarray, int], np.ndarray],
                 rng: np.random.Generator, measurement_update: bool = True) -> None:
        _check_variant(variant)
        if particles < 1:
            raise MmslamError(f"particles={particles}: expected at least 1 particle")
        self.scn = scn
        self.fp = scn.filter
        self.variant = variant
        self.P = int(particles)
        self.R = np.asarray(R, float)
        self.bs = scn.bs_array
        self.dt = scn.dt
        self.pd_fn = pd_fn
        self.rng = rng
        self.update = measurement_update
        with np.errstate(divide="ignore"):
            self.log_clutter = float(np.log(clutter_intensity)) if clutter_intensity > 0 else -np.inf
        self.types: tuple[int, ...] = (VA, SP) if variant == "baseline" else (VA, SP, VS)
        self.s = init_particles(prior_mean, scn.filter.prior_std, self.P, rng)
        self.s[:, 3] = wrap_angle(self.s[:, 3])
        self.logw = np.full(self.P, -np.log(self.P))
        self.maps: dict[int, GM] = {t: empty((self.P,), 0, _dims(t)) for t in self.types}
        self._prev_Z: np.ndarray | None = None
        self._k = -1
        from .vs import predict_vs  # local: keeps the import graph flat for tests of other parts
        self._predict_vs = predict_vs

    # ------------------------------------------------------------------ stages
    def predict(self, speed: float, turn_rate: float) -> None:
        """Prediction from step k-1 to k: births from ``Z_{k-1}``, particles, map survival / VS motion."""
        fp = self.fp
        births: dict[int, GM] = {}
        if self.update and self._prev_Z is not None and self._prev_Z.shape[0]:
            kinds = tuple(sorted({VA if t == VA else SP for t in self.types}))  # SP and VS share the inversion
            moments = birth_moments_by_kind(self.s, self._prev_Z, self.R, kinds, self.bs)
            for t in self.types:
                kind = VA if t == VA else SP
                births[t] = birth_from_moments(self.s, *moments[kind], t, fp.birth_weight, self.pd_fn,
                                               fp.vs_birth_velocity_var, fp.vs_birth_turn_std)
        self.s = propagate(self.s, speed, turn_rate, self.dt, np.asarray(self.scn.sensor.vehicle_noise_std),
                           self.rng)
        if not self.update:
            return
        for t in self.types:
            g = self.maps[t]
            if t == VS:
                q, dither = np.asarray(fp.vs_process_std), np.asarray(fp.vs_dither)
                # dithering T_d: every VS Gaussian (scope "all") or only the births (scope "newborn")
                old_dither = dither if fp.vs_dither_scope == "all" else None
                if g.capacity:
                    g = self._predict_vs(g, self.dt, fp.p_survival, q, old_dither)
                if t in births and births[t].capacity:
                    g = concat(g, self._predict_vs(births[t], self.dt, fp.p_survival, q, dither))
            else:
                g = predict_static(g, fp.p_survival)
                if t in births:
                    g = concat(g, births[t])
            self.maps[t] = g

    def correct(self, Z: np.ndarray, R_z: np.ndarray | None = None) -> None:
        """PHD correction of every map with ``Z (J, 5)`` and the particle weight update.

        ``R_z``: ``(J, 5, 5)`` one filter covariance per measurement (power-aware sensor model),
        or None for the filter's constant ``R``.

        Raises FloatingPointError if a corrected map breaks the PHD-mass invariant (more than
        the predicted mass plus ``J`` for some particle; :func:`~mmslam.slam.gmphd.check_phd_mass`).
        """
        J = Z.shape[0]
        if not self.update or J == 0:
            return
        R = self.R if R_z is None else np.asarray(R_z, float).reshape(J, 5, 5)
        p_bs = self.pd_fn(self.s[:, 0:3], np.broadcast_to(self.bs, (self.P, 3)), BS)
        bs_term = bs_logterm(self.s, Z, R, self.bs, np.asarray(p_bs, float))
        terms = [type_terms(self.maps[t], t, self.s, Z, R, self.bs, self.pd_fn,
                            vs_extent(self.scn) if t == VS else None) for t in self.types]
        lpsi = log_psi(terms, bs_term, self.log_clutter, (self.P, J))
        for tc in terms:
            g = corrected_gm(tc, Z, lpsi, prune=self.fp.prune)
            check_phd_mass(tc.g, g, J, tc.lm_type, self._k)  # cheap; fails loudly on corrupted weights
            self.maps[tc.lm_type] = g
        self.logw = self.logw + lpsi.sum(axis=1)

    def reduce(self) -> None:
        """``prune_merge`` of every map (prune, merge, cap, max position trace)."""
        fp = self.fp
        for t in self.types:
            g = self.maps[t]
            if g.capacity:  # prune_merge prunes first and trims the slots to the live count
                g = prune_merge(g, fp.prune, fp.merge, fp.max_gaussians, fp.max_trace, pos_dims=3)
            self.maps[t] = g

    def estimate(self, w: np.ndarray) -> tuple[np.ndarray, np.ndarray, dict[int, GM]]:
        """Weighted-mean state, its covariance and the averaged maps for normalised weights ``w``."""
        fp, fu = self.fp, self.scn.fusion
        mean = weighted_state_mean(self.s, w)
        cov = weighted_state_cov(self.s, w, mean)
        avg = {}
        for t in self.types:
            g = self.maps[t]
            avg[t] = (average_map(g, w, fu.average_prune, fp.merge, fp.max_gaussians, fp.max_trace)
                      if g.capacity else empty((), 0, _dims(t)))
        return mean, cov, avg

    def resample(self, w: np.ndarray) -> tuple[float, bool]:
        """Systematic resampling if ``ESS < resample_ess P``; returns ``(ESS, resampled)``."""
        e = ess(w)
        if e < self.fp.resample_ess * self.P:
            idx = systematic_resample(w, self.rng)
            self.s = self.s[idx]
            self.maps = {t: _take(g, idx) for t, g in self.maps.items()}
            self.logw = np.full(self.P, -np.log(self.P))
            return e, True
        return e, False

    # ------------------------------------------------------------------ one step
    def step(self, Z: np.ndarray, speed: float | None = None, turn_rate: float | None = None,
             R_z: np.ndarray | None = None) -> StepEstimate:
        """One vehicle-step: predict (unless first step), correct with ``Z (J, 5)``, reduce, estimate, resample.

        ``speed`` (m/s) and ``turn_rate`` (rad/s) are the known inputs of the previous step
        (ignored on the first call). The measurements are kept for the next step's births.
        ``R_z``: ``(J, 5, 5)`` per-measurement covariances for the correction (births keep ``R``).
        """
        Z = np.asarray(Z, float).reshape(-1, 5)
        if not np.isfinite(Z).all():
            raise FloatingPointError("non-finite measurement passed to the filter")
        self._k += 1
        if self._k > 0:
            if speed is None or turn_rate is None:
                raise ValueError("speed and turn_rate are required after the first step")
            self.predict(float(speed), float(turn_rate))
        self.correct(Z, R_z)
        self.reduce()
        self.logw, w = normalise_log_weights(self.logw)
        mean, cov, avg = self.estimate(w)
        e, res = self.resample(w)
        self._prev_Z = Z
        return StepEstimate(mean, cov, avg, e, res)

    def downlink(self, fused: dict[int, GM], ego: tuple[np.ndarray, np.ndarray] | None = None) -> None:
        """Overwrite every particle's map of each type in ``fused`` by the fused map (paper III-B2).

        ``ego``: this vehicle's posterior as a VS Gaussian (mean ``(7,)``, covariance ``(7, 7)``);
        with ``fusion.downlink_ego = "remove"`` (variant ``proposed``, part of its ``F'_AA``
        countermeasure) the VS components matched to it are dropped first.
        """
        fu = self.scn.fusion
        for t, g in fused.items():
            if t not in self.maps:
                continue
            if (t == VS and ego is not None and self.variant == "proposed" and fu.downlink_ego == "remove"
                    and g.capacity):
                from .fusion import remove_ego

                g = remove_ego(g, ego[0], ego[1], fu.msm_position)
            self.maps[t] = _broadcast_gm(g, self.P)


# ====================================================================== fusion center
def vs_extent(scn: Scenario) -> np.ndarray | None:
    """``(3, 3)`` covariance of a VS bounce point about the car's antenna (``filter.vs_extent_std``), None if 0."""
    h, v = (float(x) for x in scn.filter.vs_extent_std)
    return np.diag([h * h, h * h, v * v]) if (h or v) else None


def filter_detect_probs(scn: Scenario) -> dict[int, float]:
    """Type code -> the filter's detection probability inside the FOV (``filter.p_detect_<type>``)."""
    fp = scn.filter
    return {BS: fp.p_detect_bs, VA: fp.p_detect_va, SP: fp.p_detect_sp, VS: fp.p_detect_vs}


def ego_gaussian(mean: np.ndarray, cov: np.ndarray, q_std: Sequence[float]) -> tuple[np.ndarray, np.ndarray]:
    """The ego vehicle posterior as a 7-D VS Gaussian ``[x, y, z, vx, vy, vz, xi]``.

    Mean: position, velocity ``zeta [cos alpha, sin alpha, 0]``, turn rate ``xi`` (so the
    Cartesian CT of the VS model reproduces the polar CT exactly). Covariance: the particle
    covariance mapped linearly (velocity from the heading variance) plus ``diag(q_std^2)``,
    one step of the VS process noise, as a floor (the particle covariance is singular: z,
    speed and turn rate are known exactly).
    """
    a, v = mean[3], mean[4]
    m = np.array([mean[0], mean[1], mean[2], v * np.cos(a), v * np.sin(a), 0.0, mean[5]])
    J = np.zeros((7, 7))
    J[0, 0] = J[1, 1] = J[2, 2] = 1.0
    J[3, 3], J[3, 4] = -v * np.sin(a), np.cos(a)
    J[4, 3], J[4, 4] = v * np.cos(a), np.sin(a)
    J[6, 5] = 1.0
    C = J @ cov @ J.T + np.diag(np.asarray(q_std, float) ** 2)
    return m, 0.5 * (C + C.T)


class FusionCenter:
    """The BS's fused maps (batch ``()``) and the per-variant fusion rules (paper III-B, IV-B)."""

    def __init__(self, scn: Scenario, variant: str) -> None:
        from . import fusion as fu_mod  # written by another module owner

        self.fu_mod = fu_mod
        self.scn = scn
        self.variant = variant
        self.types = (VA, SP) if variant == "baseline" else (VA, SP, VS)
        self.maps: dict[int, GM] = {t: empty((), 0, _dims(t)) for t in self.types}

    def predict(self) -> None:
        """Proposed: predict the fused VS map one step at the BS (no birth)."""
        if self.variant == "proposed" and self.maps[VS].capacity:
            fp = self.scn.filter
            self.maps[VS] = self.fu_mod.predict_bs_vs(self.maps[VS], self.scn.dt, fp.p_survival,
                                                      np.asarray(fp.vs_process_std), 1)

    def fuse(self, avg_maps: dict[int, GM], fov_positions: np.ndarray, ego_mean: np.ndarray,
             ego_cov: np.ndarray) -> dict[int, GM]:
        """Fuse one vehicle's upload into the BS maps; returns the fused maps (for the downlink).

        Args:
            avg_maps: type -> the vehicle's averaged map (batch ``()``).
            fov_positions: ``(n, 3)`` the vehicle's estimated positions since its last upload
                (accumulated FOV: radius ``fov_range`` for SP/VS, infinite for VA).
            ego_mean, ego_cov: the vehicle's state posterior mean ``(7,)`` and covariance.
        """
        fm, fu, fp = self.fu_mod, self.scn.fusion, self.scn.filter
        r_fov = self.scn.sensor.fov_range
        for t in self.types:
            bs_map = self.maps[t]
            ue = avg_maps.get(t, empty((), 0, _dims(t)))
            radius = np.inf if t == VA else r_fov
            # accumulated FOV (paper's footnote): where p_D reached gamma_D since the last upload
            inside = fm.in_accumulated_fov(bs_map.m[..., 0:3], fov_positions, radius)
            inside &= filter_detect_probs(self.scn)[t] >= fu.gamma_detect
            pairs = None
            if t == VS and self.variant == "proposed":
                em, ec = ego_gaussian(ego_mean, ego_cov, fp.vs_process_std)
                ext = vs_extent(self.scn)
                if ext is not None:  # others see this car where its body reflects, not at its antenna
                    ec = ec.copy()
                    ec[0:3, 0:3] += ext
                ue = fm.ego_vs_average(ue, em, ec, fu.msm_position)
                fused, pairs = fm.fuse_vs(bs_map, ue, inside, fu.msm_position, fu.msm_velocity,
                                          fu.beta_inside_fov, with_pairs=True)
            else:
                fused, pairs = fm.fuse_aa(bs_map, ue, inside, fu.msm_position, with_pairs=True)
            gate = fp.merge
            if t == VS:  # fusion.vs_reduction: merge the matched pairs only, or every pair within a gate
                if fu.vs_reduction == "matched":
                    fused, gate = merge_pairs(fused, pairs), 0.0
                else:
                    gate = fu.vs_merge_gate
            if fused.capacity:
                fused = prune_merge(fused, fu.average_prune, gate, fp.max_gaussians, fp.max_trace, pos_dims=3)
            self.maps[t] = fused
        return dict(self.maps)


# ====================================================================== evaluation helpers
EXTRACTIONS = ("threshold", "vo_ma")


def estimates_of(g: GM, threshold: float, extraction: str = "threshold") -> tuple[np.ndarray, np.ndarray]:
    """Landmark estimates of one mixture: positions ``(n, 3)`` and the weight of the Gaussian behind each.

    ``threshold`` (TWC2020): one estimate per component with ``w > threshold``.
    ``vo_ma`` (Vo & Ma 2006, Table III): ``round(w)`` estimates at the mean of each component with
    ``w > 0.5``, so a Gaussian of weight ~2 (two merged targets) counts twice.
    """
    if extraction not in EXTRACTIONS:
        raise MmslamError(f"extraction={extraction!r}: expected one of {', '.join(EXTRACTIONS)}")
    if extraction == "threshold":
        sel = g.mask & (g.w > threshold)
        return g.m[sel][:, 0:3], g.w[sel]
    sel = np.nonzero(g.mask & (g.w > 0.5))[0]
    reps = np.maximum(np.rint(g.w[sel]).astype(int), 1)
    idx = np.repeat(sel, reps)
    return g.m[idx][:, 0:3], g.w[idx]


def cardinality(g: GM) -> float:
    """Expected number of landmarks of a map PHD: the sum of its weights."""
    return float(np.sum(np.where(g.mask, g.w, 0.0)))


VA_KEY_RESOLUTION = 1e-3
"""m: VAs whose image sources agree to this are one landmark (facades of several objects on one plane)."""


def truth_keys(paths: dict[str, np.ndarray]) -> np.ndarray:
    """Evaluation identity of each path row's landmark, ``(n,)`` str.

    A VA is its image source (the BS mirrored in a plane), so two facades of different buildings
    on one plane are one VA: VA rows are keyed by the image position rounded to
    :data:`VA_KEY_RESOLUTION`; every other type by its ``landmark_id``.
    """
    ids = np.asarray(paths["landmark_id"]).astype(str)
    typ = np.asarray(paths["type"])
    out = ids.astype(object)
    va = np.nonzero(typ == VA)[0]
    if va.size:
        xyz = np.stack([np.asarray(paths[c], float)[va] for c in ("lm_x", "lm_y", "lm_z")], -1)
        q = np.rint(xyz / VA_KEY_RESOLUTION).astype(np.int64)
        out[va] = [f"va@{a},{b},{c}" for a, b, c in q]
    return out.astype(str)


def _truth_rows(paths: dict[str, np.ndarray]) -> tuple[np.ndarray, ...]:
    """``step, type, rx (n,)``, evaluation keys ``(n,)`` (:func:`truth_keys`) and landmark positions ``(n, 3)``."""
    xyz = np.stack([np.asarray(paths["lm_x"], float), np.asarray(paths["lm_y"], float),
                    np.asarray(paths["lm_z"], float)], -1)
    return np.asarray(paths["step"]), np.asarray(paths["type"]), np.asarray(paths["rx"]), truth_keys(paths), xyz


def _first_seen(paths: dict[str, np.ndarray], n_veh: int, steps: int, positions: np.ndarray,
                sensor: Any) -> dict[int, list[dict[str, tuple[int, np.ndarray]]]]:
    """type -> per vehicle: landmark id -> (first step it could be detected by that vehicle, position).

    A landmark counts from the first step it is in the vehicle's paths *and* inside its FOV
    (``fov_detect_prob > 0`` at the true antenna ``positions (steps, n_veh, 3)``): a ray tracer
    reports scatterers at any range, but the sensor (and so the filter) only sees them within
    ``fov_range``; a landmark the vehicle could never measure is not a missed one.
    """
    from .sensor import fov_detect_prob

    out: dict[int, list[dict[str, tuple[int, np.ndarray]]]] = {VA: [{} for _ in range(n_veh)],
                                                               SP: [{} for _ in range(n_veh)]}
    step, typ, rx, ids, xyz = _truth_rows(paths)
    sel = np.nonzero(((typ == VA) | (typ == SP)) & (step < steps))[0]
    if sel.size:
        u = positions[step[sel], rx[sel]]
        pd = np.where(typ[sel] == VA, fov_detect_prob(u, xyz[sel], VA, sensor),
                      fov_detect_prob(u, xyz[sel], SP, sensor))
        sel = sel[np.asarray(pd, float) > 0]
    for i in sel[np.argsort(step[sel], kind="stable")]:
        d = out[int(typ[i])][int(rx[i])]
        if ids[i] not in d:
            d[ids[i]] = (int(step[i]), xyz[i])
    return out


def _visible_counts(paths: dict[str, np.ndarray], n_veh: int, steps: int, positions: np.ndarray,
                    sensor: Any) -> dict[int, np.ndarray]:
    """type -> ``(steps, n_veh + 1)`` number of distinct landmarks of that type each vehicle could
    detect at each step (in its paths at that step and inside its FOV); the last column counts the
    union over vehicles (the fused map's). Tells forgetting (truth counts a landmark from its first
    sighting on) from never seeing."""
    from .sensor import fov_detect_prob

    step, typ, rx, ids, xyz = _truth_rows(paths)
    out = {}
    for t in EVAL_TYPES:
        sel = np.nonzero((typ == t) & (step < steps))[0]
        sets = [[set() for _ in range(n_veh + 1)] for _ in range(steps)]
        if sel.size:
            pd = np.asarray(fov_detect_prob(positions[step[sel], rx[sel]], xyz[sel], t, sensor), float)
            for i in sel[pd > 0]:
                sets[int(step[i])][int(rx[i])].add(ids[i])
                sets[int(step[i])][n_veh].add(ids[i])
        out[t] = np.array([[len(c) for c in row] for row in sets], np.int32).reshape(steps, n_veh + 1)
    return out


def _truth_static(seen: dict[str, tuple[int, np.ndarray]], k: int) -> np.ndarray:
    pts = [p for s, p in seen.values() if s <= k]
    return np.array(pts, float).reshape(-1, 3)


def _merge_seen(per_veh: list[dict[str, tuple[int, np.ndarray]]]) -> dict[str, tuple[int, np.ndarray]]:
    out: dict[str, tuple[int, np.ndarray]] = {}
    for d in per_veh:
        for key, (s, p) in d.items():
            if key not in out or s < out[key][0]:
                out[key] = (s, p)
    return out


def _schedule(scn: Scenario, n_veh: int, steps: int) -> list[set[int]]:
    fu = scn.fusion
    starts = fu.start if len(fu.start) == n_veh else tuple(fu.start[0] for _ in range(n_veh))
    return [set(range(int(s), steps, int(fu.period))) for s in starts]


class _Table:
    """Column accumulator for the Result tables."""

    def __init__(self) -> None:
        self.cols: dict[str, list] = {}

    def add(self, **kw: Any) -> None:
        for k, v in kw.items():
            self.cols.setdefault(k, []).append(v)

    def extend(self, n: int, **kw: Any) -> None:
        for k, v in kw.items():
            vals = list(np.broadcast_to(np.asarray(v, dtype=object if isinstance(v, str) else None), (n,)))
            self.cols.setdefault(k, []).extend(vals)

    def arrays(self, dtypes: dict[str, Any]) -> dict[str, np.ndarray]:
        out = {}
        for k, dt in dtypes.items():
            vals = self.cols.get(k, [])
            out[k] = np.array(vals, dtype=object) if dt is object else np.asarray(vals, dtype=dt)
        return out


_VEH_DT = {"step": np.int32, "vehicle": np.int16, "x": float, "y": float, "z": float, "heading": float,
           "bias": float, "true_x": float, "true_y": float, "true_z": float, "true_heading": float,
           "true_bias": float, "pos_err": float, "heading_err": float, "bias_err": float}
_MET_DT = {"step": np.int32, "map": object, "type": object, "gospa": float, "loc": float, "missed": float,
           "false": float, "n_est": np.int32, "n_true": np.int32, "card": float,
           "n_visible": np.int32}
_LM_DT = {"step": np.int32, "map": object, "type": object, "x": float, "y": float, "z": float,
          "weight": float}


# ====================================================================== run
def run_filter(scn: Scenario, states: np.ndarray, paths: dict[str, np.ndarray], variant: str = "baseline",
               particles: int = 300, seed: int = 0, steps: int | None = None,
               include_types: Sequence[int] = (BS, VA, SP, VS), meta: dict[str, Any] | None = None,
               *, measurement_update: bool = True) -> Result:
    """Run cooperative MM-PHD-SLAM on noise-free paths (no cache needed).

    Args:
        scn: scenario (sensor, filter, fusion, evaluation parameters).
        states: ``(steps, n_veh, 7)`` true vehicle states (cache ``states``).
        paths: ``paths`` table columns for (at least) these steps.
        variant: ``baseline`` | ``cm1`` | ``proposed``, or the reference ``odometry`` (dead
            reckoning: the same prior and inputs, ``measurement_update=False``).
        particles: particles per vehicle (>= 1).
        seed: Monte Carlo seed (measurement noise, clutter, detections, prior, filter draws).
        steps: number of steps to run (default all of ``states``).
        include_types: path types turned into measurements (e.g. ``(0, 1, 2)`` drops VS rows).
        meta: extra entries for ``Result.meta`` (e.g. the cache hash).
        measurement_update: False runs dead reckoning (prediction only).

    Returns:
        A :class:`~mmslam.slam.result.Result` (tables documented in :mod:`mmslam.slam.result`).
    """
    from .gospa import gospa
    from .sensor import fov_detect_prob, simulate_measurements

    t0 = time.perf_counter()
    label = variant
    if variant == "odometry":
        variant, measurement_update = "baseline", False
    _check_variant(variant)
    if isinstance(particles, bool) or not isinstance(particles, (int, np.integer)) or particles < 1:
        raise MmslamError(f"particles={particles!r}: expected an integer >= 1")
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
    steps = int(steps)
    bad = [t for t in include_types if t not in (BS, VA, SP, VS, 4)]
    if bad:
        raise MmslamError(f"include_types {list(include_types)}: unknown type codes {bad}; use 0 BS, 1 VA, 2 SP, 3 VS, 4 OTHER")
    states = states[:steps]
    step_col = np.asarray(paths["step"])
    sub = {k: np.asarray(v)[step_col < steps] for k, v in paths.items()}

    ss = np.random.SeedSequence(int(seed))
    s_meas, s_prior, *s_veh = ss.spawn(2 + n_veh)
    meas = simulate_measurements(scn, states, sub, np.random.default_rng(s_meas), include_types=tuple(include_types))
    true = np.asarray(meas.true_states, float)
    R = scn.filter.r_scale * np.asarray(meas.R, float)
    sensor = scn.sensor

    pd_type = filter_detect_probs(scn)

    def pd_fn(u: np.ndarray, x: np.ndarray, t: int) -> np.ndarray:
        """The filter's p_D: its per-type probability inside the FOV (sensor's range gate), 0 outside."""
        inside = np.asarray(fov_detect_prob(u, x, t, sensor), float) > 0
        return np.where(inside, pd_type[int(t)], 0.0)

    prior_rng = np.random.default_rng(s_prior)
    prior_std = np.asarray(scn.filter.prior_std, float)
    filters = []
    for n in range(n_veh):
        prior_mean = true[0, n] + prior_rng.standard_normal(7) * prior_std
        filters.append(LocalFilter(scn, variant, int(particles), prior_mean, R, float(meas.clutter_intensity),
                                   pd_fn, np.random.default_rng(s_veh[n]), measurement_update))
    center = FusionCenter(scn, variant) if measurement_update else None
    sched = _schedule(scn, n_veh, steps)
    acc_fov: list[list[np.ndarray]] = [[] for _ in range(n_veh)]
    seen = _first_seen(sub, n_veh, steps, true[:steps, :, 0:3], sensor)
    seen_all = {t: _merge_seen(seen[t]) for t in (VA, SP)}
    visible = _visible_counts(sub, n_veh, steps, true[:steps, :, 0:3], sensor)
    ev = scn.evaluation
    thresholds = {VA: scn.filter.threshold_va, SP: scn.filter.threshold_sp, VS: scn.filter.threshold_vs}
    names = scn.vehicle_names
    vt, mt, lt = _Table(), _Table(), _Table()
    empty3 = np.zeros((0, 3))

    def record_map(k: int, name: str, maps: dict[int, GM], truth: dict[int, np.ndarray], col: int) -> None:
        for t in EVAL_TYPES:
            if t in maps:
                X, wts = estimates_of(maps[t], thresholds[t], scn.filter.extraction)
                card = cardinality(maps[t])
            else:
                X, wts, card = empty3, np.zeros(0), 0.0
            Y = truth[t]
            g = gospa(Y, X, ev.gospa_c, ev.gospa_p, ev.gospa_alpha)  # (truth, estimates)
            mt.add(step=k, map=name, type=TYPE_NAMES[t], gospa=float(g.d), loc=float(g.loc),
                   missed=float(g.missed), false=float(g.false), n_est=len(X), n_true=len(Y), card=card,
                   n_visible=int(visible[t][k, col]))
            for x, wv in zip(X, wts):
                lt.add(step=k, map=name, type=TYPE_NAMES[t], x=x[0], y=x[1], z=x[2], weight=float(wv))

    for k in range(steps):
        if center is not None and k > 0:
            center.predict()
        for n, f in enumerate(filters):
            sel = np.asarray(meas.mask[k, n], bool)
            Z = np.asarray(meas.z[k, n], float)[sel]
            spd, tr = (true[k - 1, n, 4], true[k - 1, n, 5]) if k > 0 else (None, None)
            # power-aware sensor: each measurement's own (CRB) covariance, scaled like R
            R_z = (None if meas.R_meas is None else
                   scn.filter.r_scale * np.einsum("ja,ab->jab", np.asarray(meas.R_meas[k, n], float)[sel], np.eye(5)))
            est = f.step(Z, spd, tr, R_z)
            ts = true[k, n]
            vt.add(step=k, vehicle=n, x=est.mean[0], y=est.mean[1], z=est.mean[2], heading=est.mean[3],
                   bias=est.mean[6], true_x=ts[0], true_y=ts[1], true_z=ts[2], true_heading=ts[3],
                   true_bias=ts[6], pos_err=float(np.linalg.norm(est.mean[0:3] - ts[0:3])),
                   heading_err=float(wrap_angle(est.mean[3] - ts[3])), bias_err=float(est.mean[6] - ts[6]))
            others = np.array([true[k, i, 0:3] for i in range(n_veh) if i != n]).reshape(-1, 3)
            near = others[np.linalg.norm(others - ts[0:3], axis=1) <= sensor.fov_range] if len(others) else empty3
            record_map(k, names[n], est.avg_maps,
                       {VA: _truth_static(seen[VA][n], k), SP: _truth_static(seen[SP][n], k), VS: near}, n)
            acc_fov[n].append(est.mean[0:3])
            if center is not None and k in sched[n]:
                fused = center.fuse(est.avg_maps, np.array(acc_fov[n]), est.mean, est.cov)
                f.downlink(fused, ego_gaussian(est.mean, est.cov, scn.filter.vs_process_std))
                acc_fov[n] = []
        fused_maps = center.maps if center is not None else {}
        record_map(k, "fused", fused_maps, {VA: _truth_static(seen_all[VA], k), SP: _truth_static(seen_all[SP], k),
                                            VS: true[k, :, 0:3].copy()}, n_veh)

    from mmslam import __version__ as mm_version  # noqa: PLC0415

    md: dict[str, Any] = {"variant": label, "particles": int(particles), "seed": int(seed),
                          "scenario": scn.name, "cache": None, "source": None, "steps": steps, "vehicle_names": list(names),
                          "include_types": [int(t) for t in include_types],
                          "measurement_update": bool(measurement_update),
                          "fusion_start": int(min(scn.fusion.start)),
                          "wall_time_s": time.perf_counter() - t0, "mmslam_version": mm_version}
    md.update(meta or {})
    md["wall_time_s"] = time.perf_counter() - t0
    return Result(vt.arrays(_VEH_DT), mt.arrays(_MET_DT), lt.arrays(_LM_DT), md)


def run_slam(cache_dir: str | Path, variant: str = "baseline", particles: int = 300, seed: int = 0,
             steps: int | None = None, include_types: Sequence[int] = (BS, VA, SP, VS),
             overrides: Sequence[str] = ()) -> Result:
    """Load a path cache and run :func:`run_filter` on it.

    ``overrides``: ``section.key=value`` strings (e.g. ``"fusion.vs_reduction=gate"``) applied to
    the cached scenario's [sensor], [filter], [fusion] and [evaluation] parameters
    (:func:`mmslam.scenes.scenario.with_overrides`); they change the filter run, never the trace.

    Raises:
        CacheError: the cache is missing, corrupt or of another schema (from ``load_cache``).
        MmslamError: ``particles < 1``, an unknown variant or a bad ``steps``.
    """
    if variant not in REFERENCES:
        _check_variant(variant)
    if isinstance(particles, bool) or not isinstance(particles, (int, np.integer)) or particles < 1:
        raise MmslamError(f"particles={particles!r}: expected an integer >= 1")
    from mmslam.raytrace.cache import load_cache

    cache = load_cache(cache_dir)
    scn = with_overrides(cache.scenario, list(overrides))
    if scn.geometry_hash() != cache.scenario.geometry_hash():
        raise MmslamError(f"--set {', '.join(overrides)}: changes the traced scenario (the cache's truth); "
                          "trace a new cache with that scenario instead")
    meta = {"cache": cache.manifest.get("config_hash"), "source": cache.manifest.get("source"),
            "cache_path": str(cache.path), "overrides": list(overrides)}
    return run_filter(scn, cache.states, cache.paths, variant=variant, particles=particles,
                      seed=seed, steps=steps, include_types=include_types, meta=meta)
