"""The local filter of one vehicle: an RBPF with one GM-PHD map per landmark type (docs/design.md section 6).

One local step (:meth:`LocalFilter.step`), for vehicle ``n`` at step ``k``:

1. prediction (``k > 0``): birth Gaussians from the previous step's measurements and particle
   states (each type's ``birth`` on its geometry's inversion, weight ``filter.birth_weight``, or the type's
   ``birth_existence`` for a birth that is a new landmark by its own measurement, :mod:`~mmslam.slam.phd.first_detection`;
   with ``filter.adaptive_birth`` times ``c(z) / psi(z)`` of the particle's correction of that ``z``, step 2);
   particles propagated by the CT model (eq. 1) with the known speed / turn rate of step ``k-1``
   and the vehicle's process noise (:func:`~mmslam.slam.filter.process_noise.vehicle_process_std`); each map through its
   type's ``predict``
   (static: times ``p_S``, eq. 4; VS: coordinated turn with process noise and dithering, eq. 9);
2. correction with ``Z_k`` (eqs. 5 / 10, CKF per Gaussian, filter noise ``R = r_scale R_true``);
   particle log-weights ``+= sum_z log psi(z)`` (product form, as the authors' code; the paper's
   eq. 6 writes a sum). Corrected components below the prune threshold are never materialised;
3. reduction per type (``prune_merge``: prune, merge, cap, max_trace);
4. estimates with the corrected weights: weighted-mean state, averaged maps (eq. 7,
   ``average_map`` with ``fusion.average_prune``; with ``fusion.average_by_label`` the particles'
   copies of one labelled landmark pooled first); a first-detection landmark whose averaged Beta count rose since its
   birth is confirmed (:attr:`LocalFilter.unconfirmed`, :mod:`~mmslam.slam.filter.confirmation`);
5. systematic resampling when ``ESS < resample_ess P`` (no roughening: the process noise added
   at every prediction keeps the particles diverse).

Which maps a filter keeps, and whether it corrects at all, is its variant's
(:class:`~mmslam.slam.specs.variants.VariantSpec`); what each map does, its type's
(:class:`~mmslam.slam.specs.landmarks.LandmarkSpec`).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from mmslam.errors import MmslamError
from mmslam.model import Bounce
from mmslam.scenes.scenario import Scenario

from ..phd.birth import birth_moments_by_kind
from ..phd.first_detection import new_landmark_births
from ..models.dynamics import wrap_angle
from ..core.gm import (LABEL_BITS, GM, compact, concat, drop_dead_slots, ego_label, empty, is_ego_label, random_walk,
                       with_labels)
from ..phd.gmphd import correct
from ..specs.landmarks import LandmarkSpec, check_type_rows, trace_cap
from ..models.measurement import BS
from .confirmation import Unconfirmed, detected_since_birth, fresh_labels
from .known_map import KnownMap
from .rbpf import (ess, init_particles, normalise_log_weights, propagate, systematic_resample,
                   weighted_state_cov, weighted_state_mean)
from ..phd.reduction import average_map, prune_merge
from ..specs.variants import VariantSpec, get_variant


def _broadcast_gm(g: GM, n: int) -> GM:
    """A single mixture (batch ``()``) copied to every one of ``n`` particles (batch ``(n,)``)."""
    return g.take((None,)).take(np.zeros(n, int))


def _take(g: GM, idx: np.ndarray) -> GM:
    return g.take(idx)


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
        variant: a :class:`~mmslam.slam.specs.variants.VariantSpec` or its name (``baseline`` | ``cm1``
            | ``proposed`` | ...): which maps (``map_types``) and the downlink rule.
        particles: number of particles ``P``.
        prior_mean: ``(7,)`` the initial state estimate.
        R: ``(5, 5)`` the filter's measurement covariance (already scaled by ``r_scale``).
        clutter_intensity: ``c(z)`` (per unit of measurement-space volume).
        pd_fn: ``pd_fn(vehicle_pos (..., 3), lm_pos (..., 3), lm_type) -> (...)`` detection
            probability (typically :func:`mmslam.slam.sim.sensor.fov_detect_prob`).
        rng: this filter's random generator.
        measurement_update: False for dead reckoning (no correction, births or map).
        vehicle: the vehicle's index in ``[0, 2^23)``; with ``fusion.average_by_label`` its births are
            labelled ``vehicle * 2^40 + i`` (``i = 0, 1, ...``), unique across the vehicles of a run.
        known_map: an oracle map of one type (:mod:`mmslam.slam.filter.known_map`): before every correction
            that type's map in every particle is replaced by the landmarks ``known_map`` gives this vehicle
            at this step; None (default): every map is estimated.
        process_std: ``(7,)`` the vehicle's process noise std (units of ``sensor.vehicle_noise_std``); None
            (default): ``scn.sensor.vehicle_noise_std`` as it stands; a cooperative run passes each vehicle's
            :func:`~mmslam.slam.filter.process_noise.vehicle_process_std` (the truth's model, the odometry, the slope).
    """

    def __init__(self, scn: Scenario, variant: str | VariantSpec, particles: int, prior_mean: np.ndarray,
                 R: np.ndarray, clutter_intensity: float,
                 pd_fn: Callable[[np.ndarray, np.ndarray, int], np.ndarray],
                 rng: np.random.Generator, measurement_update: bool = True, vehicle: int = 0,
                 known_map: KnownMap | None = None, process_std: np.ndarray | None = None) -> None:
        spec = get_variant(variant)
        if particles < 1:
            raise MmslamError(f"particles={particles}: expected at least 1 particle")
        if not 0 <= int(vehicle) < 1 << (63 - LABEL_BITS):  # its labels: non-negative int64, none NO_LABEL
            raise MmslamError(f"vehicle={vehicle}: expected a vehicle index in [0, {1 << (63 - LABEL_BITS)})")
        self.scn = scn
        self.fp = scn.filter
        self.variant = spec
        self.P = int(particles)
        self.R = np.asarray(R, float)
        self.bs = scn.bs_array
        self._bs_rows = np.broadcast_to(self.bs, (self.P, 3))  # the BS position of every particle (read-only view)
        self.dt = scn.dt
        self.pd_fn = pd_fn
        self.rng = rng
        self.update = measurement_update
        with np.errstate(divide="ignore"):
            self.log_clutter = float(np.log(clutter_intensity)) if clutter_intensity > 0 else -np.inf
        self.specs: dict[int, LandmarkSpec] = {t.code: t for t in spec.types()}
        """type code -> spec of every map this filter keeps"""
        self.types: tuple[int, ...] = tuple(self.specs)
        self._extent = {t: s.extent(scn) for t, s in self.specs.items()}
        self._body = {t: s.body(scn) for t, s in self.specs.items()}
        self._missed = {t: s.type_params(scn).missed for t, s in self.specs.items()}
        """type code -> its missed-detection rule (``filter.types.<T>.missed``)"""
        self._association = {t: s.type_params(scn).association for t, s in self.specs.items()}
        """type code -> its measurement association (``filter.types.<T>.association``)"""
        self._tail = {t: (s.type_params(scn).tail_weight, s.type_params(scn).tail_scale) for t, s in self.specs.items()}
        """type code -> the heavy tail ``(e, K)`` of its likelihood (``filter.types.<T>.tail_weight``, ``tail_scale``)
        """
        self._walk = {t: s.type_params(scn).drift_std ** 2 * scn.dt for t, s in self.specs.items()}
        """type code -> the variance (m^2 per axis) of its Gaussians' random walk over one step
        (``filter.types.<T>.drift_std``)"""
        self._follow = {t: s.type_params(scn).follow_std ** 2 for t, s in self.specs.items()}
        """type code -> the variance (m^2 per axis) of the follow offset of its update
        (``filter.types.<T>.follow_std``)"""
        self._weight_offset = {t: s.type_params(scn).weight_std ** 2 for t, s in self.specs.items()}
        """type code -> the variance (m^2 per axis) of its offset in the particle weight only
        (``filter.types.<T>.weight_std``)"""
        self._weight_share = {t: s.type_params(scn).weight_share for t, s in self.specs.items()}
        """type code -> the share ``lambda`` of that offset in its particle-weight likelihood
        (``filter.types.<T>.weight_share``)"""
        check_type_rows(scn)  # e.g. no random walk on a moving type
        self.s = init_particles(prior_mean, scn.filter.prior_std, self.P, rng)
        self.s[:, 3] = wrap_angle(self.s[:, 3])
        self.logw = np.full(self.P, -np.log(self.P))
        self._labels = bool(scn.fusion.average_by_label)
        self._fleet: GM | None = None
        """the other cars as the downlinks told them (``filter.band_cars``, :meth:`_roster`), batch ``()``, predicted
        with the VS motion since; None before the first downlink"""
        self.maps: dict[int, GM] = {t: empty((self.P,), 0, s.state_dim, with_label=self._labels)
                                    for t, s in self.specs.items()}
        self._prev_Z: np.ndarray | None = None
        self._unexplained: np.ndarray | None = None
        """``(P, J)`` ``c(z_j) / psi_p(z_j)`` of the last correction (``filter.adaptive_birth``), else None"""
        self.adaptive_birth = bool(self.fp.adaptive_birth) and self.log_clutter > -np.inf
        """``filter.adaptive_birth`` where it is defined: without clutter ``c / psi`` is 0, so every measurement
        births at ``filter.birth_weight`` (the caller says so, ``meta["adaptive_birth"]``)"""
        self._k = -1
        self.vehicle = int(vehicle)
        if known_map is not None and known_map.type_code not in self.specs:
            raise MmslamError(f"known map of type code {known_map.type_code}: variant {spec.name!r} keeps no such map")
        self.known_map = known_map
        self.process_std = np.asarray(scn.sensor.vehicle_noise_std if process_std is None else process_std, float)
        if self.process_std.shape != (7,) or not (self.process_std >= 0).all():
            raise MmslamError(f"process_std={self.process_std.tolist()}: expected 7 stds >= 0")
        self.unconfirmed = Unconfirmed(self.types)
        """this car's first-detection landmarks not yet detected at a second step (:mod:`.confirmation`)"""
        self._confirm = {t: sp.pd_beta_prior(scn)[0] for t, sp in self.specs.items()
                         if self._labels and sp.type_params(scn).birth_existence > 0
                         and sp.pd_beta_prior(scn) is not None}
        """type code -> prior Beta ``s0``: the types whose first-detection births are confirmed before other cars
        get them (labels and a Beta detection model needed)"""
        self._next_label = int(vehicle) << LABEL_BITS
        self._ego_label = ego_label(vehicle)  # the last of the vehicle's range: not a birth's
        """the label of the next birth (``fusion.average_by_label``)"""

    # ------------------------------------------------------------------ stages
    def predict(self, speed: float, turn_rate: float) -> None:
        """Prediction from step k-1 to k: births from ``Z_{k-1}``, particles, the random walk of a static type's
        Gaussians (``filter.types.<T>.drift_std``; the births not), map survival / VS motion."""
        births: dict[int, GM] = {}
        if self.update and self._prev_Z is not None and self._prev_Z.shape[0]:
            # one inversion per path geometry (SP and VS share SCATTER), the types' births from it
            # filter.band_cars asks the single-scatter point of each path where some type has first-detection births
            scat = int(Bounce.SCATTER)
            first = any(sp.type_params(self.scn).birth_existence > 0 for sp in self.specs.values())
            cars = self._cars() if first else None
            kinds = tuple(sorted({int(sp.geometry) for sp in self.specs.values()} | ({scat} if cars is not None
                                                                                      else set())))
            moments = birth_moments_by_kind(self.s, self._prev_Z, self.R, kinds, self.bs)
            for t, sp in self.specs.items():
                geo = int(sp.geometry)
                # the births that are new landmarks by their own measurement (filter.types.<T>.birth_existence)
                new = (new_landmark_births(self.s, self._prev_Z, self.R, moments[geo], geo, self.bs,
                                           self.fp.vs_birth_height, sp.merge_gate(self.scn), self.maps[t],
                                           cars, 0.5 * float(self.fp.vs_body[0]),
                                           moments[scat] if cars is not None else None)
                       if sp.type_params(self.scn).birth_existence > 0 else None)
                # a birth column dead in every particle (e.g. outside the FOV) is no slot of the map
                births[t] = drop_dead_slots(sp.birth(self.s, moments[geo], sp, self.scn, self.pd_fn,
                                                     self._unexplained, new))
                if self._labels:  # one label per birth column: the same landmark hypothesis in every particle
                    births[t], self._next_label = with_labels(births[t], self._next_label)
                    if t in self._confirm:
                        self.unconfirmed.born(t, fresh_labels(births[t], self.fp.birth_weight))
                    if self._next_label > self._ego_label:  # 2^40 - 1 births: never in practice
                        raise MmslamError(f"vehicle {self._ego_label >> LABEL_BITS} ran out of birth labels")
        self.s = propagate(self.s, speed, turn_rate, self.dt, self.process_std, self.rng)
        if not self.update:
            return
        if self._fleet is not None:
            self._fleet = next(sp for sp in self.specs.values() if sp.moving).predict(self._fleet, None, self.scn)
        for t, sp in self.specs.items():
            g = self.maps[t] if self._walk[t] == 0 else random_walk(self.maps[t], self._walk[t])
            self.maps[t] = sp.predict(g, births.get(t), self.scn)
            if sp.survive is not None:
                self.maps[t] = sp.survive(self.maps[t], self.s, self.scn)

    def _cars(self) -> GM | None:
        """The cars ``filter.band_cars`` asks whether a bounce in the car band could be a car's, batch ``(P,)``: each
        particle's VS map (the first moving type's) and the fleet as the downlinks told it (:attr:`_fleet`: a car
        the VS map has lost to its missed detections since, 95 % a step, is still on the road). None without that
        option, or until the downlinks have brought every other car of the scenario (a car that has not yet
        uploaded could be anywhere). The cars are known by their ego labels, which the fused VS map carries with
        ``fusion.average_by_label`` in a variant whose upload places its own car (``proposed``'s ``F'_AA``, eq. (11));
        otherwise no other car is ever known and the option does not act (with one car it acts at once)."""
        if not self.fp.band_cars or self._fleet is None:
            return None
        if np.unique(self._fleet.label[self._fleet.mask]).size < len(self.scn.vehicles) - 1:
            return None
        vs = next(self.maps[t] for t, sp in self.specs.items() if sp.moving)
        fleet = _broadcast_gm(self._fleet, self.P)
        return GM(np.concatenate([vs.w, fleet.w], -1), np.concatenate([vs.m, fleet.m], -2),
                  np.concatenate([vs.P, fleet.P], -3), np.concatenate([vs.mask, fleet.mask], -1))

    def _roster(self, fused_vs: GM) -> GM:
        """The fleet after a downlink of ``fused_vs`` (batch ``()``): each other car's own estimate (its ego-labelled
        Gaussian, eq. (11)) as this map holds it, or as the last downlink that held it did, predicted since. The BS's
        fused VS map can lose a car between two of its uploads (another car's upload that misses it halves it, the
        paper's ``beta`` inside the FOV), but the car is still on the road. Without labels no car is known as one.
        A car no later downlink brings again stays, its spread growing with the VS process noise at each step."""
        g = fused_vs
        if g.label is None:
            return GM(np.zeros(0), np.zeros((0, g.dim)), np.zeros((0, g.dim, g.dim)), np.zeros(0, bool),
                      label=np.zeros(0, np.int64))
        new = g.mask & is_ego_label(g.label) & (g.label != self._ego_label)
        parts = [(g.w[new], g.m[new], g.P[new], g.label[new])]
        if self._fleet is not None:
            old = self._fleet.mask & ~np.isin(self._fleet.label, g.label[new])
            parts.append((self._fleet.w[old], self._fleet.m[old], self._fleet.P[old], self._fleet.label[old]))
        w, m, P, lab = (np.concatenate(a) for a in zip(*parts))
        return GM(w, m, P, np.ones(w.shape, bool), label=lab)

    def correct(self, Z: np.ndarray, R_z: np.ndarray | None = None) -> None:
        """PHD correction of every map with ``Z (J, 5)`` and the particle weight update.

        ``R_z``: ``(J, 5, 5)`` one filter covariance per measurement (power-aware sensor model),
        or None for the filter's constant ``R``.

        Raises FloatingPointError if a corrected map breaks the PHD-mass invariant (more than
        the predicted mass plus ``J`` for some particle; :func:`~mmslam.slam.phd.gmphd.check_phd_mass`).
        """
        J = Z.shape[0]
        if not self.update:
            return
        # J = 0 still corrects: every detectable Gaussian was missed, w <- (1 - p_D) w (eq. (5) with
        # an empty set); the particle weights are unchanged (an empty product)
        R = self.R if R_z is None or J == 0 else np.asarray(R_z, float).reshape(J, 5, 5)
        if self.known_map is not None:  # the oracle map of one type, given afresh at every step
            t = self.known_map.type_code
            self.maps[t] = self.known_map.mixture(self._k, self.vehicle, self.P,
                                                  self.specs[t].pd_beta_prior(self.scn) is not None, self._labels)
        p_bs = self.pd_fn(self.s[:, 0:3], self._bs_rows, BS)
        corrected, lpsi, own = correct({t: self.maps[t] for t in self.types}, self.s, Z, R, self.bs, self.pd_fn,
                                       p_bs, self.log_clutter, self.fp.prune, self._extent, self._k, self.specs,
                                       self._body, self._missed, self._association, self._tail, self._follow,
                                       self._weight_offset, self._weight_share)
        self.maps.update(corrected)
        self.logw = self.logw + lpsi.sum(axis=1)  # paper eq. (6)
        if self.adaptive_birth:  # the share of each z_j that no map and not the BS explained: its births' weight
            self._unexplained = np.exp(np.minimum(self.log_clutter - own, 0.0))

    def reduce(self) -> None:
        """``prune_merge`` of every map (prune, merge, cap, max position trace of the moving types,
        :func:`~mmslam.slam.specs.landmarks.trace_cap`)."""
        fp = self.fp
        for t in self.types:
            g = self.maps[t]
            if g.capacity:  # prune_merge prunes first and trims the slots to the live count
                g = prune_merge(g, fp.prune, self.specs[t].merge_gate(self.scn), fp.max_gaussians,
                                trace_cap(self.specs[t], self.scn), pos_dims=3)
            self.maps[t] = g

    def estimate(self, w: np.ndarray) -> tuple[np.ndarray, np.ndarray, dict[int, GM]]:
        """Weighted-mean state, its covariance and the averaged maps for normalised weights ``w``."""
        fp, fu = self.fp, self.scn.fusion
        mean = weighted_state_mean(self.s, w)
        cov = weighted_state_cov(self.s, w, mean)
        avg = {}
        for t in self.types:
            g = self.maps[t]
            avg[t] = (average_map(g, w, fu.average_prune, self.specs[t].merge_gate(self.scn), fp.max_gaussians,
                                  trace_cap(self.specs[t], self.scn), by_label=fu.average_by_label)
                      if g.capacity else empty((), 0, self.specs[t].state_dim, with_label=self._labels))
            if t in self._confirm:
                self.unconfirmed.detected(t, detected_since_birth(avg[t], self._confirm[t]))
        return mean, cov, avg

    def resample(self, w: np.ndarray) -> tuple[float, bool]:
        """Systematic resampling if ``ESS < resample_ess P``; returns ``(ESS, resampled)``."""
        e = ess(w)
        if e < self.fp.resample_ess * self.P:
            idx = systematic_resample(w, self.rng)
            self.s = self.s[idx]
            self.maps = {t: _take(g, idx) for t, g in self.maps.items()}
            if self._unexplained is not None:
                self._unexplained = self._unexplained[idx]
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
        Z = np.array(Z, dtype=float).reshape(-1, 5)  # a copy: kept for the next step's births
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
        for a variant with ``downlink_ego_removal`` (``proposed``, part of its ``F'_AA``
        countermeasure) the type's ``remove_ego`` (VS, with ``fusion.downlink_ego = "remove"``)
        drops the components matched to it first. The fused map's labels (``fusion.average_by_label``)
        go to every particle with it: after a downlink the particles' copies of a landmark share one.
        A type with ``filter.types.<TYPE>.keep_tentative`` keeps each particle's own Gaussians lighter than
        ``fusion.average_prune`` (the tentative ones, which the fused map prunes) after the fused ones.
        """
        for t, g in fused.items():
            if t not in self.maps:
                continue
            sp = self.specs[t]
            if sp.remove_ego is not None and ego is not None and self.variant.downlink_ego_removal and g.capacity:
                g = sp.remove_ego(g, ego, self.scn)
            if sp.moving and self.fp.band_cars:
                self._fleet = self._roster(g)
            if g.pd_beta is not None and self.fp.pd_beta_downlink == "prior":
                g = g.copy()
                g.pd_beta[...] = sp.pd_beta_prior(self.scn)
            own = self.maps[t]
            tentative = (own.mask & (own.w < self.scn.fusion.average_prune)
                         if self.fp.type_params(sp.name).keep_tentative and own.capacity else None)
            self.maps[t] = _broadcast_gm(g, self.P)
            if tentative is not None and tentative.any():
                kept = GM(own.w, own.m, own.P, tentative, own.pd_beta, own.label)
                self.maps[t] = compact(concat(self.maps[t], kept))
