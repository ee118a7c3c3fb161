"""Typed scenario model, loaded from TOML and validated (docs/design.md sections 3 and 5).

A scenario is everything needed to build a scene, trace it and run the filter on it:
geometry (BS, buildings, scatterers, optional ground, vehicles and their motion), time grid,
carrier frequency, the sensor model and the filter / fusion / evaluation parameters.

Global frame: x east, y north, z up, metres; angles in radians; times in seconds.

Only :func:`load_scenario` / :func:`load_preset` / :func:`resolve_scenario` create scenarios
from user input; every error they raise is a :class:`~mmslam.errors.ConfigError` whose message
names the file, the key and what is expected.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import tomllib
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from mmslam.errors import ConfigError
from mmslam.limits import COORD_MAX, MAX_PARTICLES, MAX_SEED, MAX_STEPS
from mmslam.model import landmark_type_names, unknown_type_row
from mmslam.scenes.params import ParamSpec, check_value, did_you_mean, iter_params, param, param_rows, parse_override

WAYPOINT_MOTION = "pure-pursuit-ct-2"
"""How a ``motion = "waypoints"`` vehicle drives its route (:func:`mmslam.scenes.driving.drive_route`),
part of :meth:`Scenario.geometry_hash` for a scenario with such a vehicle: a cache traced with another rule
(before it, cars kept to the polyline and their heading jumped at its corners) is not resumed with this one."""

MATERIALS = ("concrete", "metal", "brick", "wood", "glass", "marble", "plasterboard", "ceiling_board",
             "floorboard", "chipboard", "very_dry_ground")
"""ITU-R P.2040 materials valid at 28 GHz that scenario files may name (Sionna's ``itu_*``).

``medium_dry_ground`` and ``wet_ground`` are deliberately absent: they are only defined up to
10 GHz in ITU-R P.2040 and Sionna rejects them at 28 GHz.
"""


@dataclass(frozen=True)
class Building:
    """An axis-aligned box building (walls are its faces). ``min``/``max`` corners in m."""

    name: str
    min: tuple[float, float, float]
    max: tuple[float, float, float]
    material: str = "concrete"


@dataclass(frozen=True)
class Scatterer:
    """A small static scatter object (SP). ``position`` is its reference point (centre), m.

    ``shape`` is ``box`` (cube of edge ``size``) or ``cylinder`` (diameter and height ``size``).
    """

    name: str
    position: tuple[float, float, float]
    size: float = 1.0
    shape: str = "box"
    material: str = "metal"
    scattering_coefficient: float = 0.7


@dataclass(frozen=True)
class Ground:
    """A horizontal ground plane at height ``z`` (m), ``extent`` m square around the origin."""

    z: float = 0.0
    extent: float = 400.0
    material: str = "concrete"


@dataclass(frozen=True)
class Vehicle:
    """A car with a roof antenna.

    ``initial_state = [x, y, z, heading, speed, turn_rate, clock_bias]`` (m, m, m, rad, m/s,
    rad/s, m). The antenna is at ``(x, y, z)``; the car body is a ``length x width x height``
    box whose roof is ``roof_gap`` m below the antenna. ``motion`` is ``ct`` (coordinated turn
    from the initial state) or ``waypoints`` (the ``waypoints`` polyline driven at the plan ``speed`` from the
    first waypoint, corners rounded: :func:`mmslam.scenes.driving.drive_route`).
    """

    name: str
    initial_state: tuple[float, ...]
    motion: str = "ct"
    waypoints: tuple[tuple[float, float], ...] = ()
    length: float = 4.5
    width: float = 1.8
    height: float = 1.5
    roof_gap: float = 0.05
    material: str = "metal"
    scattering_coefficient: float = 0.5


@dataclass(frozen=True)
class SensorParams:
    """Sensor model (per Monte Carlo run): noise, detection, FOV, clutter, clock bias.

    The true clock bias follows a random walk with the last entry of ``vehicle_noise_std``.
    """

    toa_std: float = param(0.1, "measurement noise std of the TOA", "m", lo=0.0, lo_open=True, hi=100.0)
    angle_std: float = param(0.01, "measurement noise std of each of the four angles", "rad", lo=0.0,
                             lo_open=True, hi=1.0)
    p_detect: float = param(0.95, "detection probability of a landmark inside the FOV", "", probability=True)
    fov_range: float = param(50.0, "SP/VS visibility radius (BS and VAs are always in the FOV)", "m",
                             lo=0.0, lo_open=True, hi=1e5)
    clutter_mean: float = param(1.0, "Poisson mean of clutter measurements per vehicle and step", "",
                                lo=0.0, hi=1000.0)
    clutter_toa_max: float = param(200.0, "upper end of the uniform clutter TOA", "m", lo=0.0,
                                   lo_open=True, hi=1e6)
    vehicle_noise_std: tuple[float, ...] = param(
        (0.2, 0.2, 0.0, 1e-3, 0.0, 0.0, 0.2), "process noise std of [x, y, z, heading, speed, turn rate, "
        "clock bias] per step: the true clock bias's random walk (every scene), the truth's motion noise of a ct car "
        "with true_process_noise, and the filter's process noise of such a car (a car whose truth drives the motion "
        "model exactly gets filter.motion_jitter_std in x, y and heading, and so does such a car in an x, y or heading "
        "entry of 0 here)", "m, m, m, rad, m/s, rad/s, m", lo=0.0,
        hi=1e3, length=7)
    odometry_noise_std: tuple[float, ...] = param(
        (0.0, 0.0), "std of the odometry the filter takes as its known inputs each step: speed, turn rate (white "
        "noise on the true values; 0: exact, the paper's known inputs; a stopped car reads speed 0, no car a "
        "negative one); the filter's "
        "process noise grows to match (mmslam.slam.filter.process_noise.vehicle_process_std)", "m/s, rad/s", lo=0.0, hi=100.0,
        length=2)
    true_process_noise: bool = param(False, "add the process noise (all but the clock bias) to the "
                                     "true, traced trajectory too (off: the traced trajectory is the truth)")
    emit_other: bool = param(False, "also emit paths labelled OTHER (higher-order bounces) as measurements")
    model: str = param("constant", "detection / noise model: constant (p_detect, toa_std, angle_std for every "
                       "path), link (p_D and noise std from each path's power via the link budget below: "
                       "mmslam.slam.sim.sensor.LinkBudget) or estimated (a channel estimator on the received "
                       "MIMO-OFDM pilots: mmslam.slam.sim.estimated_sensor)", choices=("constant", "link", "estimated"))
    tx_power_dbm: float = param(20.0, "link model: BS transmit power", "dBm", lo=-50.0, hi=80.0)
    tx_gain_dbi: float = param(18.06, "link model: BS array gain (8 x 8 elements: 10 log10 64)", "dBi",
                               lo=-20.0, hi=60.0)
    rx_gain_dbi: float = param(12.04, "link model: vehicle array gain (4 x 4 elements)", "dBi", lo=-20.0, hi=60.0)
    bandwidth_hz: float = param(400e6, "link model: signal bandwidth (noise bandwidth and delay accuracy)", "Hz",
                                lo=0.0, lo_open=True, hi=1e11)
    noise_figure_db: float = param(9.0, "link model: receiver noise figure", "dB", lo=0.0, hi=40.0)
    processing_gain_db: float = param(0.0, "link and estimated models: coherent integration gain beyond one pilot "
                                      "OFDM symbol (more pilot symbols / snapshots)", "dB", lo=0.0, hi=80.0)
    pfa: float = param(1e-4, "link model: false-alarm probability of the detector per resolution cell", "",
                       lo=0.0, lo_open=True, hi=1.0, hi_open=True)
    tx_array: int = param(8, "link model: BS array elements per axis (AOD accuracy)", "", lo=2, hi=1024)
    rx_array: int = param(4, "link model: vehicle array elements per axis (AOA accuracy)", "", lo=2, hi=1024)
    est_subcarriers: int = param(256, "pilot subcarriers K over the bandwidth, one pilot OFDM symbol (estimated "
                                 "model: its delay window c K / bandwidth, 192 m at 256 and 400 MHz; link model: "
                                 "the symbol's integration gain 10 log10 K in the SNR)", "", lo=8, hi=4096)
    est_pfa: float = param(0.01, "estimated model: CFAR false-alarm probability per vehicle and step on noise "
                           "only (the estimator's detection threshold)", "", lo=0.0, lo_open=True, hi=1.0,
                           hi_open=True)
    est_max_paths: int = param(20, "estimated model: at most this many estimates per vehicle and step", "",
                               lo=1, hi=200)
    est_resolve: float = param(2.0, "estimated model: non-maximum suppression radius: an estimate within this "
                               "many resolution cells, in each of the five axes at once (delay c / bandwidth, "
                               "each array's spatial frequency 2 / elements), of a stronger kept estimate of the "
                               "same link is dropped before the filter (0: off). NOMP returns a diffuse cluster "
                               "around one path as several estimates; the filter's model has at most one "
                               "measurement per landmark and step (docs/estimator.md, section 3b)", "cells",
                               lo=0.0, hi=64.0)
    est_toa_floor: float = param(0.05, "estimated model: floor of an estimate's TOA standard deviation, added in "
                                 "quadrature to its Fisher-information value: a component the estimator cannot "
                                 "resolve (closer than c / bandwidth) biases the estimate by an amount set by the "
                                 "two components' relative phase (in phase: about half their gap later; near "
                                 "anti-phase: earlier than the first by more than the gap), e.g. the car roof's reflection of a roof antenna; "
                                 "5 cm is about the measured RMS of that error (docs/estimator.md, section 3c)",
                                 "m", lo=0.0, hi=100.0)


@dataclass(frozen=True)
class TypeParams:
    """The filter's parameters of one landmark type: a row ``[filter.types.<TYPE>]`` (e.g. ``VA``)."""

    p_detect: float = param(0.95, "the filter's detection probability of a landmark of this type inside the FOV "
                            "(BS: of the LOS path, lower it where buildings often block the LOS; VA: lower it in "
                            "cities, where a wall is visible for a few steps at a time, so that a VA outlives "
                            "missed detections and, below fusion.gamma_detect, is never judged a false alarm by "
                            "the fusion's accumulated-FOV rule)", "", probability=True)
    threshold: float = param(0.55, "estimate-extraction weight threshold of the type's maps (unused for the known "
                             "BS)", "", lo=0.0, hi=10.0)
    p_detect_source: str = param("value", "where the filter's p_D of this type comes from: value (p_detect), or "
                                 "link: under a power-aware sensor model (link, estimated) the link budget's mean "
                                 "detection probability of the type's paths inside the FOV on the run's paths "
                                 "(their traced power through the sensor's link budget: its predicted-SNR "
                                 "detection model, not the run's detections), clipped to [0.01, 0.99]; under the "
                                 "constant model p_detect (docs/estimator.md, 6b)", choices=("value", "link"))
    missed: str = param("phd", "the weight of a Gaussian of this type after a missed detection inside the FOV: phd "
                        "((1 - p_D) w, eq. (5), the paper) or bernoulli (w (1 - p_D) / (1 - w p_D) for w < 1; for w >= 1 "
                        "the mass w is kept, less the shares its detections take: the Gaussian read as one landmark "
                        "that exists with probability min(w, 1), the missed-detection update of a Bernoulli filter as "
                        "in BP-SLAM: a confirmed landmark is not decayed by misses, only by p_S, so a wall out of sight "
                        "for a while stays mapped; docs/city-slam.md)", choices=("phd", "bernoulli"))
    association: str = param("phd", "how a scan's measurements update the type's Gaussians: phd (every Gaussian "
                             "takes its share of every measurement, eq. (5), the paper) or exclusive (each Gaussian "
                             "one landmark that gives at most one measurement, each measurement from at most one "
                             "landmark: marginal association probabilities by belief propagation, as in BP-SLAM; "
                             "a second measurement near a landmark then births a second landmark instead of pulling "
                             "the first; docs/city-slam.md)", choices=("phd", "exclusive"))
    tail_weight: float = param(0.0, "weight e of a heavy tail in the likelihood of a measurement given one of the "
                               "type's Gaussians: (1 - e) N(z; zhat, S(P)) + e N(z; zhat, S(tail_scale P)), each "
                               "the CKF update of the Gaussian with P or tail_scale P, the posterior the two "
                               "moment-matched into one Gaussian (a landmark mapped further off than its covariance "
                               "says then pulls a car less, and its covariance grows); 0: the paper's Gaussian "
                               "likelihood. The VA default, 0.2 with the merge gate 6, is chosen and checked on city "
                               "scenes in docs/city-slam.md", "", lo=0.0, hi=0.5)
    tail_scale: float = param(4.0, "factor on the Gaussian's covariance in the tail of the likelihood (tail_weight > "
                              "0; 4: twice the standard deviation)", "", lo=1.0, hi=100.0)
    drift_std: float = param(0.0, "std of a random walk of a static landmark's position per square root of time: at "
                             "every local prediction (births excepted) each live Gaussian of the type gets dt "
                             "drift_std^2 added to the variance of its x, y and z. A VA of a facade built of facets a "
                             "degree or two apart moves as the specular point moves along it (munich2: six image "
                             "sources, each within 1.2 m of the next); with a walk the map follows it. 0: a landmark "
                             "that does not move (the paper, and the default: 0.42 makes the VA map help localisation "
                             "on every city scene of a declared run, but canyon's two image sources 1.53 m apart "
                             "merge and its VA map passes its target; docs/city-slam.md). A moving type (VS) has its own motion noise (filter.vs_process_std) "
                             "and must leave it 0", "m/s^0.5", lo=0.0, hi=100.0)
    follow_std: float = param(0.0, "std of the offset by which the image point a scan sees departs from the mapped "
                              "one, which the update follows: the gain and likelihood of a Gaussian of the type take "
                              "follow_std^2 more variance in x, y and z, the covariance kept is the estimate's own for "
                              "that gain (its Joseph form), a missed Gaussian keeps its own. A VA of a facade built of "
                              "facets moves as the specular point moves along it; the map follows the facet seen "
                              "without its covariance growing, so merging still keeps apart image sources a metre or "
                              "two apart (unlike drift_std). 0: the paper's update, and the default: 0.6 keeps "
                              "canyon's and munich's map targets in a declared run, but the copies of a VA then "
                              "fragment past 0.6 of the empty map on three written scenes (docs/city-slam.md). A "
                              "moving type (VS) must leave it 0", "m", lo=0.0, hi=100.0)
    weight_std: float = param(0.0, "std of the offset between the image point a scan sees and the mapped one, in "
                              "the particle weight only (eq. (6)): each detected term's likelihood in log psi(z) is "
                              "taken with weight_std^2 more variance in x, y and z (on top of follow_std^2; the heavy "
                              "tail's part scales it by tail_scale too), at the share weight_share; each particle's "
                              "map update (eq. (5)) is unchanged. A map sure of a point that moves along a facade of "
                              "facets (munich2: NEES 6-17; sf3: a facade stepped 2.8 m in depth) then pulls the cars "
                              "less. 0: the paper's weight. The VA default, 0.6 at the share 0.2, passed its declared "
                              "run (session 26, 15 city scenes, two never run): no scene localises worse, seven "
                              "better, and the VA map helps on seven of thirteen written scenes (five without it); "
                              "the offset alone (share 1) had cost florence3 0.8 cm twice (docs/city-slam.md). A "
                              "moving type (VS) must leave it 0", "m", lo=0.0, hi=100.0)
    weight_share: float = param(1.0, "share lambda of the weight offset in each detected term's likelihood in the "
                                "particle weight: (1 - lambda) N(z; zhat, S(P)) + lambda N(z; zhat, S(P + "
                                "weight_std^2 I)), the image point seen departing from the mapped one by the offset "
                                "at a share lambda of the detections; with one type offset, psi(z) in the weight is "
                                "then (1 - lambda) psi(z) + lambda psi_w(z). 1: the offset at every detection "
                                "(weight_std alone); 0: no offset; no effect while weight_std = 0. A share below 1 "
                                "keeps the sharp likelihood of a map that is right, which the offset alone flattens; "
                                "the VA default is 0.2 (docs/city-slam.md, session 26)", "", lo=0.0, hi=1.0)
    keep_tentative: bool = param(False, "at a downlink the vehicle keeps its particles' own tentative Gaussians of "
                                 "this type (weight below fusion.average_prune, which the fused map prunes: a birth "
                                 "detected once or twice) beside the fused map it receives, instead of losing them to "
                                 "the overwrite (paper III-B2): with a filter.prune low enough that a birth outlives a "
                                 "few missed steps, a wall a car sees at two steps apart can then be confirmed. "
                                 "False: the paper's downlink. The VA default is true (with filter.prune 1e-5), by "
                                 "a declared run on twenty city scenes (docs/city-slam.md, session 28)")
    birth_existence: float = param(0.0, "weight of a birth that is a new landmark by its own measurement, in place of "
                                   "filter.birth_weight (times c(z) / psi(z) with filter.adaptive_birth): its AOD fits "
                                   "the AOD the birth predicts (chi-square, 2 degrees of freedom, within its 99.9 % "
                                   "point), its path bounces more than filter.vs_birth_height above or below the "
                                   "antenna (within that band it may come off a car body), no Gaussian of the "
                                   "particle's map nor another birth of the scan lies within the type's merge gate of "
                                   "it, and the BS's line of sight does not explain it "
                                   "(mmslam.slam.phd.first_detection). Such a landmark is mapped from its first "
                                   "detection instead of its second: a wall a car passes once. With labels "
                                   "(fusion.average_by_label) and a Beta p_D (filter.pd_model beta) another car gets "
                                   "it through the downlink only once it is confirmed, detected at a second step by "
                                   "the car that bore it or matched at the BS with another car's "
                                   "(mmslam.slam.filter.confirmation); the BS map holds it from the start. 0: every "
                                   "birth at filter.birth_weight (the paper). Meant for a static type (a VS is born "
                                   "in the car band, which the second condition rules out). The VA default is 0.9, "
                                   "by a declared run on twenty city scenes (docs/city-slam.md, session 32)", "",
                                   lo=0.0,
                                   hi=1.0)
    merge: float | None = param(None, "merge gate U of the type's maps (local reduction, averaged map, fused map); "
                                "not set: filter.merge. The VA default, 6, keeps apart image sources that U = 49 "
                                "joins (canyon: two 1.53 m apart) also when the heavy tail (tail_weight) has grown "
                                "their covariances; with exclusive association the fragments a tight gate used to "
                                "leave are not created (docs/city-slam.md); negative: filter.merge", "", lo=-1.0,
                                hi=1e6)

    def merge_gate(self, default: float) -> float:
        """The merge gate of the type: :attr:`merge`, or ``default`` (``filter.merge``) when it is not set or negative."""
        return float(default) if self.merge is None or self.merge < 0 else float(self.merge)


DEFAULT_TYPE_PARAMS: dict[str, TypeParams] = {
    "BS": TypeParams(),
    "VA": TypeParams(p_detect=0.1, threshold=0.5, missed="bernoulli", association="exclusive", tail_weight=0.2,
                     weight_std=0.6, weight_share=0.2, keep_tentative=True, birth_existence=0.9, merge=6.0),
    "SP": TypeParams(), "VS": TypeParams(p_detect_source="link")}
"""The built-in rows of ``[filter.types]`` (TWC2020 values, but VA: p_detect 0.1, the mean of a new VA's Beta
prior, threshold 0.5, the Bernoulli missed-detection rule, the exclusive association, the heavy tail 0.2, the weight
offset 0.6 m at a share 0.2, the tentative Gaussians kept through the downlink and the merge gate 6, the city
defaults of docs/city-slam.md; the ``paper`` preset sets 0.95 / 0.7 / phd / phd / 0 / 0 / false / 49;
VS: p_D from the
link budget under a power-aware sensor, docs/estimator.md 6b). A file's row replaces the keys it gives; a type
without a row (e.g. a newly registered one) gets :class:`TypeParams`'s defaults."""

TYPE_PARAM_ALIASES: dict[str, tuple[str, str]] = {
    f"{k}_{t.lower()}": (t, k) for k, ts in (("p_detect", ("BS", "VA", "SP", "VS")), ("threshold", ("VA", "SP", "VS")),
                                            ("merge", ("VA",))) for t in ts}
"""The flat keys of mmslam 0.1 (``filter.p_detect_va``, ``threshold_sp``, ``merge_va``, ...), kept as aliases of
``filter.types.<TYPE>.<key>`` (in files, ``--set`` and attribute reads); ``merge_va`` < 0 (its old default,
"the same as filter.merge") means no merge gate of its own."""


@dataclass(frozen=True)
class FilterParams:
    """MM-PHD-SLAM parameters (TWC2020 values for ``paper``)."""

    particles: int = param(300, "particles per vehicle: the default of run_filter / run_slam and of "
                           "--particles (mmslam slam, ablate, demo) when none is given", "", lo=1, hi=MAX_PARTICLES)
    r_scale: float = param(1.0, "the filter's measurement covariance is r_scale x the true R (1: the sensor's "
                           "own; the paper's filter inflates it, 9; docs/city-slam.md)", "",
                           lo=0.0, lo_open=True, hi=1e6)
    prior_std: tuple[float, ...] = param(
        (0.3, 0.3, 0.0, 0.01, 0.0, 0.0, 0.3), "std of the initial vehicle prior around the true state "
        "[x, y, z, heading, speed, turn rate, clock bias]", "m, m, m, rad, m/s, rad/s, m", lo=0.0, hi=1e3,
        length=7)
    motion_jitter_std: tuple[float, ...] = param(
        (0.1, 1e-3), "the filter's process noise of a vehicle whose truth carries none (every waypoints car, and every ct car "
        "without sensor.true_process_noise): std per step of "
        "[x and y, heading], added in quadrature to one step of the odometry's error (sensor.odometry_noise_std); it "
        "keeps the particle cloud diverse where the car drives its motion model exactly. A ct car whose truth carries "
        "process noise gets sensor.vehicle_noise_std instead (the paper's model), except in an entry of 0 there; "
        "docs/city-slam.md",
        "m, rad", lo=0.0, hi=100.0, length=2)
    height_process: str = param("route", "the filter's height (z) process noise of each vehicle: route (the larger "
                                "of sensor.vehicle_noise_std[2] and the largest height change over one step's travel "
                                "along the vehicle's route at its speed, or in one step of the car driving it, from the road's slope: "
                                "0 on flat streets "
                                "and for ct vehicles; docs/city-slam.md) or sensor (sensor.vehicle_noise_std[2] for every "
                                "vehicle)", choices=("route", "sensor"))
    p_survival: float = param(0.99, "landmark survival probability per step", "", probability=True)
    birth_weight: float = param(1.5e-5, "weight of each birth Gaussian", "", lo=0.0, lo_open=True, hi=1.0)
    adaptive_birth: bool = param(True, "adaptive birth (Ristic, Clark, Vo & Vo 2012): the birth of a measurement z in "
                                 "a particle has weight birth_weight x c(z) / psi(z), the probability that neither "
                                 "that particle's maps nor the BS explained z at the correction that saw it, so a "
                                 "measurement of a mapped landmark births no duplicate (without clutter, "
                                 "sensor.clutter_mean = 0, c / psi is 0: the plain birth, and mmslam slam says so). "
                                 "False: every measurement births at birth_weight (the paper's). The default is true "
                                 "by a declared run on twenty city scenes: no RMSE worse, no map past its target, a "
                                 "city run 30-40% faster (docs/city-slam.md, session 29)")
    prune: float = param(1e-5, "prune Gaussians of weight below this (1e-5: a VA birth, weight birth_weight, outlives "
                         "three missed steps, so a wall seen at two steps a few apart can be confirmed; the paper's "
                         "1e-4 prunes a birth at its first miss; docs/city-slam.md, session 28)", "", lo=0.0, hi=1.0)
    merge: float = param(49.0, "merge gate U (squared Mahalanobis distance) in the reduction of the maps "
                         "of every type whose [filter.types.<TYPE>] row sets no merge of its own", "",
                         lo=0.0, hi=1e6)
    max_gaussians: int = param(50, "at most this many Gaussians per type and particle", "", lo=1, hi=10_000)
    max_trace: float = param(50.0, "drop Gaussians whose position covariance trace exceeds this "
                             "(the types of filter.max_trace_scope)", "m^2", lo=0.0, lo_open=True, hi=1e9)
    max_trace_scope: str = param("moving", "which landmark types filter.max_trace applies to: moving (the "
                                 "VS, whose covariance grows by process noise; a static VA / SP Gaussian only "
                                 "shrinks after its birth, so a cap in m^2 only drops births the sensor cannot "
                                 "resolve that well: with 2x the paper's noise every VA birth) or all (every "
                                 "type, the behaviour before issue 23); see docs/implementation-notes.md",
                                 choices=("moving", "all"))
    resample_ess: float = param(0.5, "resample when the effective sample size falls below this fraction "
                                "of the particles", "", probability=True)
    vs_process_std: tuple[float, ...] = param(
        (1.0, 1.0, 0.1, 3.0, 3.0, 0.1, 0.05), "VS process noise std of [x, y, z, vx, vy, vz, turn rate]",
        "m, m, m, m/s, m/s, m/s, rad/s", lo=0.0, hi=1e3, length=7)
    vs_birth_velocity_var: tuple[float, ...] = param(
        (100.0, 100.0, 0.09), "variance of the VS birth velocity [vx, vy, vz]", "m^2/s^2", lo=0.0, hi=1e6,
        length=3)
    vs_birth_turn_std: float = param(math.pi / 2, "std of the VS birth turn rate", "rad/s", lo=0.0,
                                     lo_open=True, hi=100.0)
    vs_dither: tuple[float, ...] = param(
        (9.0, 9.0, 0.09, 5.0, 5.0, 0.09, 0.18), "dithering T_d added to VS covariances at prediction "
        "(diagonal of [x, y, z, vx, vy, vz, turn rate])", "m^2, m^2/s^2, rad^2/s^2", lo=0.0, hi=1e6, length=7)
    pd_model: str = param("beta", "the filter's detection model inside the FOV: fixed (filter.types.<TYPE>.p_detect for "
                          "every Gaussian, the paper's) or beta (each VA / SP Gaussian learns its own p_D "
                          "from its detection history: a Beta(s, t) per Gaussian, E[p_D] = s / (s + t), "
                          "missed -> (s, t + 1), detected -> (s + 1, t); Beta-Gaussian PHD, Mahler, Vo & "
                          "Vo 2011); docs/equations.md", choices=("fixed", "beta"))
    pd_beta_count: float = param(2.0, "pd_model beta: pseudo-count s0 + t0 of a birth's Beta prior, whose mean "
                                 "is filter.types.<TYPE>.p_detect (s0 = count p_detect, t0 = count (1 - p_detect)); small: "
                                 "a Gaussian's own history soon dominates", "", lo=0.0, lo_open=True, hi=1e12)
    pd_beta_forget: float = param(1.0, "pd_model beta: each prediction multiplies a Gaussian's Beta (s, t) by "
                                  "this factor (mean kept, old detections fade; 1: a static detection "
                                  "profile)", "", lo=0.0, lo_open=True, hi=1.0)
    pd_beta_downlink: str = param("prior", "pd_model beta: the Beta of each Gaussian of the fused map a vehicle "
                                  "receives: keep (the BS's pooled history) or prior (the birth prior: "
                                  "visibility is learnt per vehicle, from its own detections)",
                                  choices=("keep", "prior"))
    vs_extent_std: tuple[float, ...] = param(
        (0.0, 0.0), "std of where on a car body a VS path bounces, about the car's antenna position "
        "[horizontal (each axis), vertical]: diag(h^2, h^2, v^2) is added to the scatter point in the VS "
        "likelihood, once (the ego Gaussian F'_AA uploads stays the antenna position); 0: point VS (exact for the analytic "
        "source)", "m", lo=0.0, hi=100.0, length=2)
    vs_body_model: str = param("auto", "where a VS path bounces in the VS likelihood: ellipsoid (at the specular "
                               "point of the car body filter.vs_body, oriented along the VS's velocity), point (at "
                               "the car's antenna: the paper's model, exact for the analytic source's point "
                               "scatterers) or auto (ellipsoid on a traced source, whose cars are meshes; point on "
                               "the analytic one); docs/city-slam.md", choices=("auto", "ellipsoid", "point"))
    vs_body: tuple[float, ...] = param(
        (4.5, 1.8, 1.5, 0.8), "the car body of a VS under vs_body_model ellipsoid: [length, width, height, depth of "
        "its centre below the antenna] (the default car of the scenario format; length 0: a point VS)", "m", lo=0.0,
        hi=100.0, length=4)
    vs_birth_height: float = param(
        3.0, "a VS is born only where the path bounced at most this far above or below the receiving antenna, and "
        "a VS Gaussian within sensor.fov_range whose height leaves that band is removed (but a car's own estimate, "
        "filter.vs_keep_cars): a car is on the road (its "
        "body spans the 1.6 m below its antenna), while a wall reflection off a roof-top BS bounces 3-15 m up, "
        "between the BS and the street (a specular point a VS would follow along the wall); docs/city-slam.md; "
        "the paper has no such gate (its presets set 1e4)", "m", lo=0.0, lo_open=True,
        hi=1e4)
    band_cars: bool = param(False, "the car band of the first-detection birth (filter.vs_birth_height about the "
                            "antenna: a path that bounces there may come off a car body) asks where the cars are: "
                            "once the downlinks have brought every other car's own estimate (each kept, predicted "
                            "with the VS motion, until a later downlink brings it again), a bounce in the band "
                            "farther horizontally than half a car's length (filter.vs_body) plus 3 standard "
                            "deviations (the car's and the bounce point's, whose angle noise grows with its range) "
                            "from every such car and every VS Gaussian of the particle's map is a wall's, not a "
                            "car's (mmslam.slam.phd.first_detection; the cars' own estimates are known by their ego "
                            "labels: fusion.average_by_label and the proposed variant's uploads, else the option does "
                            "not act). False: every bounce in the band may be a car's. An option, not the default: "
                            "a static scatterer at a car's height (a pole, a sign: the street preset's) makes the same "
                            "path, and the option takes it for a wall (docs/city-slam.md, \"Walls at a car's "
                            "height\")")
    vs_keep_cars: bool = param(True, "the VS Gaussians that are cars' own estimates (their ego labels in the "
                               "downlinked fused VS map, eq. (11); needs fusion.average_by_label, without labels "
                               "none is known as one) stay in a car's VS map wherever they stand; "
                               "filter.vs_birth_height's road band removes only the others (no effect where that band "
                               "is 1e4, as in the paper preset). On "
                               "a hill a car up the street sits more than that band above the antenna; removed, the "
                               "paths off its body birth false VAs (sf5's map 0.618 -> 0.459 of the empty map in a "
                               "declared run). False: every VS Gaussian off the band goes (before session 34); "
                               "docs/city-slam.md, \"Cars up the hill\"")
    vs_dither_scope: str = param("newborn", "which VS Gaussians get the dithering T_d at a local prediction: "
                                 "newborn (only this step's births, whose velocity and turn rate are "
                                 "unobserved) or all (every VS Gaussian at every step, the paper read "
                                 "literally); see docs/vs-fusion.md", choices=("newborn", "all"))
    extraction: str = param("threshold", "landmark estimate extraction from a map PHD: threshold (one "
                            "estimate per Gaussian with weight above filter.types.<TYPE>.threshold, TWC2020) or "
                            "vo_ma (round(w) estimates per Gaussian with w > 0.5, Vo & Ma 2006)",
                            choices=("threshold", "vo_ma"))
    types: dict[str, TypeParams] = field(default_factory=lambda: dict(DEFAULT_TYPE_PARAMS))
    """Per landmark type (name -> :class:`TypeParams`): the ``[filter.types.<TYPE>]`` rows over
    :data:`DEFAULT_TYPE_PARAMS`."""

    def type_params(self, name: str) -> TypeParams:
        """The parameters of landmark type ``name`` (its row, else :class:`TypeParams`'s defaults)."""
        return self.types.get(name) or TypeParams()

    def __getattr__(self, key: str) -> float:
        """An old flat key (:data:`TYPE_PARAM_ALIASES`) read from the table (``merge_va``: -1 when not set)."""
        alias = TYPE_PARAM_ALIASES.get(key)
        if alias is None:
            raise AttributeError(f"{type(self).__name__!r} object has no attribute {key!r}")
        v = getattr(self.type_params(alias[0]), alias[1])
        return -1.0 if v is None or v < 0 else v


@dataclass(frozen=True)
class FusionParams:
    """Map fusion at the BS: schedule (steps) and thresholds."""

    period: int = param(2, "each vehicle talks to the BS every this many steps", "steps", lo=1, hi=100_000)
    start: tuple[int, ...] = param((5, 6), "first fusion step of each vehicle (one value, or one per "
                                   "vehicle; default 5 + vehicle index)", "steps", lo=0, hi=1e6)
    msm_position: float = param(20.0, "MSM threshold T_MD^L on positions", "", lo=0.0, lo_open=True, hi=1e9)
    msm_velocity: float = param(20.0, "MSM threshold T_MD^V on velocities", "", lo=0.0, lo_open=True, hi=1e9)
    beta_inside_fov: float = param(0.25, "fusion weight of an unmatched BS Gaussian inside the "
                                   "accumulated FOV", "", probability=True)
    average_prune: float = param(0.1, "pruning threshold of the averaged and fused map PHDs", "", lo=0.0,
                                 hi=1.0)
    average_by_label: bool = param(True, "averaged map (eq. 7): every Gaussian carries an identity label (a "
                                   "birth's is the same in every particle, a corrected or merged Gaussian "
                                   "keeps its slot's or cluster leader's, the downlink gives every particle "
                                   "the fused map's), and the particles' copies of one labelled landmark "
                                   "(each particle's heaviest Gaussian of the label) are moment-matched into "
                                   "one before the gated merge; off: the gate alone decides "
                                   "(docs/implementation-notes.md, VA 2 and the averaged map)")
    aa_weights: str = param("visibility", "weights of a matched pair in the AA fusion of static maps (eq. 8): "
                            "equal (1/2 each, the paper's) or visibility (each member's learnt E[p_D] over "
                            "the pair's sum, where both carry a Beta detection model, filter.pd_model = beta; "
                            "equal otherwise): a vehicle's copy of a landmark it could not see does not dilute "
                            "the copy of one that saw it; with those weights each matched pair is one landmark, "
                            "merged before the fused map is pruned, so it keeps both shares "
                            "(docs/city-slam.md)", choices=("equal", "visibility"))
    gamma_detect: float = param(0.9, "detection threshold gamma_D of the accumulated FOV: a BS-map landmark "
                                "counts as inside a vehicle's accumulated FOV if the filter's detection "
                                "probability (filter.types.<TYPE>.p_detect, 0 beyond the FOV range) reached it "
                                "at a position since the vehicle's last upload", "", probability=True)
    vs_reduction: str = param("matched", "reduction of the fused VS map after each upload: matched (merge "
                              "only the pairs F'_AA matched, then prune and cap) or gate (prune_merge with "
                              "the gate vs_merge_gate over all pairs, the local filter's reduction)",
                              choices=("matched", "gate"))
    downlink_ego: str = param("remove", "what a vehicle does with its own Gaussian in the fused VS map it "
                              "receives: remove (the F'_AA ego match, c_q = 1 -> beta = 0, applied at the "
                              "downlink as at the upload) or keep (it then decays in the local map and "
                              "can be merged with a nearby vehicle's Gaussian)", choices=("remove", "keep"))
    vs_merge_gate: float = param(49.0, "merge gate U of the fused VS map when vs_reduction = gate "
                                 "(squared Mahalanobis distance over the 7-D state)", "", lo=0.0, hi=1e6)


@dataclass(frozen=True)
class EvalParams:
    """GOSPA parameters."""

    gospa_p: float = param(2.0, "GOSPA order p", "", lo=1.0, hi=100.0)
    gospa_c: float = param(20.0, "GOSPA cut-off distance c", "m", lo=0.0, lo_open=True, hi=1e6)
    gospa_alpha: float = param(2.0, "GOSPA alpha", "", lo=0.0, lo_open=True, hi=2.0)
    truth_set: str = param("seen", "static landmarks (VA, SP) a map is scored against: seen (each from the first "
                           "step a vehicle could detect it; the fused map: any vehicle; a vehicle's map after a "
                           "downlink also: any vehicle, up to the downlink's step) or all (every VA / SP in the "
                           "run's paths, FOV or not, from step 0: the TWC2020 code's scoring)",
                           choices=("seen", "all"))
    fused_steps: str = param("all", "steps the headline mean of the fused map's GOSPA covers: all (every step from "
                             "the first upload on) or uploads (only the steps with an upload: the TWC2020 code's "
                             "mean over k = 10:2:40, its fusion steps)", choices=("all", "uploads"))
    va_resolution: float = param(1.0, "VA truths (image sources) within this of an earlier one count as one "
                                 "landmark with it (leader clustering: every member within it of the first), placed "
                                 "where a vehicle first could detect it: two parallel facades less than half of it "
                                 "apart, which the sensor cannot tell apart (docs/city-slam.md)", "m", lo=0.0,
                                 hi=100.0)


@dataclass(frozen=True)
class Scenario:
    """A complete scenario. See module docstring for frames and units."""

    name: str
    bs: tuple[float, float, float]
    vehicles: tuple[Vehicle, ...]
    buildings: tuple[Building, ...] = ()
    scatterers: tuple[Scatterer, ...] = ()
    ground: Ground | None = None
    dt: float = 0.5
    steps: int = 40
    frequency_hz: float = 28e9
    seed: int = 0
    xml_scene: str | None = None
    sensor: SensorParams = field(default_factory=SensorParams)
    filter: FilterParams = field(default_factory=FilterParams)
    fusion: FusionParams = field(default_factory=FusionParams)
    evaluation: EvalParams = field(default_factory=EvalParams)
    source_file: str = "<memory>"

    # ------------------------------------------------------------------ helpers
    @property
    def bs_array(self) -> np.ndarray:
        """BS position ``(3,)``, m."""
        return np.asarray(self.bs, dtype=float)

    @property
    def vehicle_names(self) -> list[str]:
        return [v.name for v in self.vehicles]

    def to_dict(self) -> dict[str, Any]:
        """Plain, JSON-serialisable dict that :func:`scenario_from_dict` reads back exactly."""
        d = dataclasses.asdict(self)
        d.pop("source_file", None)
        return json.loads(json.dumps(d))

    def geometry_hash(self) -> str:
        """SHA-256 (hex, 16 chars) of everything that changes traced paths.

        Covers BS, buildings, scatterers, ground, vehicles, dt, frequency, xml scene and the FOV
        range (and the true process noise, when on; with a ``waypoints`` vehicle, :data:`WAYPOINT_MOTION`); not ``steps`` (a longer trace extends a shorter one), nor sensor noise, filter,
        fusion or evaluation parameters (they act after the cache).
        """
        d = self.to_dict()
        keep = {k: d[k] for k in ("bs", "vehicles", "buildings", "scatterers", "ground", "dt",
                                  "frequency_hz", "xml_scene")}
        keep["fov_range"] = d["sensor"]["fov_range"]
        if any(v.motion == "waypoints" for v in self.vehicles):  # the truth depends on how a route is driven
            keep["waypoint_motion"] = WAYPOINT_MOTION
        if self.sensor.true_process_noise:  # the truth itself then depends on the noise draw
            keep["true_process_noise"] = [d["seed"], d["sensor"]["vehicle_noise_std"]]
        blob = json.dumps(keep, sort_keys=True).encode()
        return hashlib.sha256(blob).hexdigest()[:16]


# ====================================================================== loading
def _spec(doc: str, unit: str = "", lo: float | None = None, hi: float | None = None, *, lo_open: bool = False,
          integer: bool = False, choices: tuple[str, ...] | None = None) -> ParamSpec:
    return ParamSpec(doc, unit, lo, hi, lo_open, False, choices, integer)


_C = COORD_MAX
GEOMETRY: dict[str, tuple[str, ParamSpec]] = {
    "name": ("required", _spec("scenario name (letters, digits, '_' or '-'); names the cache directory")),
    "bs": ("required", _spec("BS antenna position [x, y, z]", "m", -_C, _C)),
    "dt": ("0.5", _spec("time step", "s", 0.0, 3600.0, lo_open=True)),
    "steps": ("40", _spec("number of time steps", "steps", 1, MAX_STEPS, integer=True)),
    "frequency_hz": ("2.8e+10", _spec("carrier frequency", "Hz", 1e8, 3e11)),
    "seed": ("0", _spec("seed of the scenario's own random draws (scatterer heights from z_range, the true "
                        "process noise)", "", 0, MAX_SEED, integer=True)),
    "xml_scene": ("none", _spec("an extra Mitsuba XML scene (path, or a Sionna scene name) traced together with "
                                "the scenario's objects")),
    "buildings[].name": ("required", _spec("unique object name")),
    "buildings[].min": ("required", _spec("box corner [x, y, z] with the smallest coordinates", "m", -_C, _C)),
    "buildings[].max": ("required", _spec("opposite box corner (max > min on every axis)", "m", -_C, _C)),
    "buildings[].material": ('"concrete"', _spec("ITU material", choices=MATERIALS)),
    "scatterers[].name": ("required", _spec("unique object name")),
    "scatterers[].position": ("required", _spec("centre [x, y, z], or [x, y] with z_range", "m", -_C, _C)),
    "scatterers[].z_range": ("none", _spec("[lo, hi]: z drawn uniformly with the scenario seed", "m", -_C, _C)),
    "scatterers[].size": ("1", _spec("cube edge, or cylinder diameter and height", "m", 0.0, 10.0, lo_open=True)),
    "scatterers[].shape": ('"box"', _spec("shape", choices=("box", "cylinder"))),
    "scatterers[].material": ('"metal"', _spec("ITU material", choices=MATERIALS)),
    "scatterers[].scattering_coefficient": ("0.7", _spec("share of diffusely scattered energy", "", 0.0, 1.0,
                                                         lo_open=True)),
    "ground.z": ("0", _spec("ground plane height", "m", -1e4, 1e4)),
    "ground.extent": ("400", _spec("side of the square ground plane around the origin", "m", 1.0, 1e5)),
    "ground.material": ('"concrete"', _spec("ITU material", choices=MATERIALS)),
    "vehicles[].name": ("required", _spec("unique object name")),
    "vehicles[].initial_state[0:3]": ("required", _spec("antenna position x, y, z", "m", -_C, _C)),
    "vehicles[].initial_state[3]": ("required", _spec("heading, counter-clockwise from +x", "rad", -100.0, 100.0)),
    "vehicles[].initial_state[4]": ("required", _spec("speed (> 0 for motion = waypoints)", "m/s", 0.0, 100.0)),
    "vehicles[].initial_state[5]": ("required", _spec("turn rate", "rad/s", -10.0, 10.0)),
    "vehicles[].initial_state[6]": ("required", _spec("initial clock bias (x c)", "m", -_C, _C)),
    "vehicles[].motion": ('"ct"', _spec("ct (coordinated turn from the initial state) or waypoints",
                                        choices=("ct", "waypoints"))),
    "vehicles[].waypoints": ("none", _spec("[[x, y], ...] or [[x, y, z], ...] polyline for motion = waypoints (first = start)",
                                           "m", -_C, _C)),
    "vehicles[].length": ("4.5", _spec("car body length", "m", 0.5, 20.0)),
    "vehicles[].width": ("1.8", _spec("car body width", "m", 0.5, 5.0)),
    "vehicles[].height": ("1.5", _spec("car body height", "m", 0.5, 5.0)),
    "vehicles[].roof_gap": ("0.05", _spec("antenna height above the roof", "m", 0.01, 1.0)),
    "vehicles[].material": ('"metal"', _spec("ITU material", choices=MATERIALS)),
    "vehicles[].scattering_coefficient": ("0.5", _spec("share of diffusely scattered energy", "", 0.0, 1.0)),
    "vehicles[].route": ("none", _spec("[[x, y], ...] (>= 2 points), with an xml_scene, instead of initial_state / "
                                       "motion / waypoints: each point is snapped to the nearest street centreline "
                                       "(free space) and the car drives along the streets between them; a point "
                                       "outside the scene's street map is refused", "m", -_C, _C)),
    "vehicles[].speed": ("6", _spec("constant speed of a route vehicle", "m/s", 0.0, 60.0, lo_open=True)),
    "vehicles[].clock_bias": ("0", _spec("initial clock bias (x c) of a route vehicle", "m", -_C, _C)),
    "vehicles[].antenna_height": ("1.6", _spec("antenna height of a route vehicle above the terrain", "m", 0.5,
                                               10.0)),
    "n_vehicles": ("none", _spec("with an xml_scene: N more cars car_000, car_001, ... on seeded random street "
                                 "routes near the BS (speeds U(4, 8) m/s, clock biases 100 m, 200 m, ...)", "", 1,
                                 100, integer=True)),
}
"""Every geometry / time key of a scenario file: (default, spec with doc, unit and bounds)."""


def _b(key: str) -> dict[str, Any]:
    """``_num`` / ``_vec`` bounds of :data:`GEOMETRY` ``key``."""
    s = GEOMETRY[key][1]
    return {"lo": s.lo, "hi": s.hi, "lo_open": s.lo_open, **({"integer": True} if s.integer else {})}


_TOP_KEYS = {"name", "bs", "vehicles", "buildings", "scatterers", "ground", "dt", "steps",
             "frequency_hz", "seed", "xml_scene", "sensor", "filter", "fusion", "evaluation", "n_vehicles"}
_ROUTE_KEYS = {"name", "route", "speed", "clock_bias", "antenna_height", "length", "width", "height", "roof_gap",
               "material", "scattering_coefficient"}


def _err(src: str, key: str, expected: str) -> ConfigError:
    return ConfigError(f"{src}: key '{key}': {expected}")


def _check_keys(src: str, where: str, table: dict, allowed: set[str]) -> None:
    for k in table:
        if k not in allowed:
            near = did_you_mean(k, allowed)
            raise _err(src, f"{where}{k}", f"unknown key; did you mean '{near}'?" if near is not None
                       else f"unknown key; expected one of {sorted(allowed)}")


def _num(src: str, key: str, v: Any, *, lo: float | None = None, hi: float | None = None,
         lo_open: bool = False, integer: bool = False) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise _err(src, key, f"expected a {'integer' if integer else 'number'}, got {v!r}")
    if integer and not float(v).is_integer():
        raise _err(src, key, f"expected an integer, got {v!r}")
    if not math.isfinite(float(v)):
        raise _err(src, key, f"expected a finite number, got {v!r}")
    if lo is not None and (v < lo or (lo_open and v == lo)):
        raise _err(src, key, f"expected a value {'>' if lo_open else '>='} {lo}, got {v!r}")
    if hi is not None and v > hi:
        raise _err(src, key, f"expected a value <= {hi}, got {v!r}")
    return int(v) if integer else float(v)


def _vec(src: str, key: str, v: Any, n: int | tuple[int, ...], lo: float | None = None,
         hi: float | None = None, lo_open: bool = False) -> tuple[float, ...]:
    lens = (n,) if isinstance(n, int) else n
    if not isinstance(v, list) or len(v) not in lens:
        raise _err(src, key, f"expected a list of {' or '.join(map(str, lens))} numbers, got {v!r}")
    return tuple(_num(src, f"{key}[{i}]", x, lo=lo, hi=hi, lo_open=lo_open) for i, x in enumerate(v))


def _str(src: str, key: str, v: Any, choices: tuple[str, ...] | None = None) -> str:
    if not isinstance(v, str):
        raise _err(src, key, f"expected a string, got {v!r}")
    if choices is not None and v not in choices:
        raise _err(src, key, f"expected one of {list(choices)}, got {v!r}")
    return v


def _name(src: str, key: str, v: Any) -> str:
    s = _str(src, key, v)
    if not s or not all(c.isalnum() or c in "_-" for c in s):
        raise _err(src, key, f"expected a non-empty name of letters, digits, '_' or '-', got {v!r}")
    return s


def _params(src: str, section: str, cls: type, table: Any) -> Any:
    """Fill a parameter dataclass from a TOML table; names, types and bounds come from :func:`param`."""
    if table is None:
        return cls()
    if not isinstance(table, dict):
        raise _err(src, section, "expected a table")
    fields = {f.name: f for f, _ in iter_params(cls)}
    _check_keys(src, f"{section}.", table, set(fields))
    kw: dict[str, Any] = {}
    for k, v in table.items():
        try:
            kw[k] = check_value(fields[k], v)
        except ValueError as e:
            raise _err(src, f"{section}.{k}", str(e)) from None
    return cls(**kw)


def _filter_params(src: str, table: Any) -> FilterParams:
    """``[filter]``: its declared parameters (:func:`_params`) and the per-type table ``[filter.types.<TYPE>]``
    (rows over :data:`DEFAULT_TYPE_PARAMS`; the old flat keys of :data:`TYPE_PARAM_ALIASES` fill it too)."""
    if table is None:
        return FilterParams()
    if not isinstance(table, dict):
        raise _err(src, "filter", "expected a table")
    table = dict(table)
    given = table.pop("types", None)
    if given is None:
        given = {}
    if not isinstance(given, dict):
        raise _err(src, "filter.types", "expected a table of [filter.types.<TYPE>] rows (p_detect, threshold, merge)")
    rows: dict[str, dict[str, Any]] = {}
    for name, row in given.items():
        _name(src, "filter.types", name)
        if name not in landmark_type_names():  # a misspelt row would set nothing, silently
            raise _err(src, f"filter.types.{name}", unknown_type_row(name))
        if not isinstance(row, dict):
            raise _err(src, f"filter.types.{name}", "expected a table (p_detect, threshold, merge)")
        rows[name] = {k: v for k, v in row.items() if v is not None}  # None: not set (a resolved scenario's JSON)
        if "merge" in row and row["merge"] is None and DEFAULT_TYPE_PARAMS.get(name, TypeParams()).merge is not None:
            rows[name]["merge"] = -1.0  # a stored "not set" (before the VA gate had a default): filter.merge
    for key in [k for k in table if k in TYPE_PARAM_ALIASES]:
        t, k = TYPE_PARAM_ALIASES[key]
        v = table.pop(key)
        if k == "merge" and isinstance(v, (int, float)) and not isinstance(v, bool) and v < 0:
            if k in rows.get(t, {}):
                continue  # the old default, "not set": the row's value stands
            v = -1.0  # the old "same as filter.merge"
        if k in rows.get(t, {}):
            raise _err(src, f"filter.{key}", f"given twice (also as filter.types.{t}.{k}); keep one")
        rows.setdefault(t, {})[k] = v
    filt = _params(src, "filter", FilterParams, table)
    types = dict(DEFAULT_TYPE_PARAMS)
    for name, row in rows.items():
        base = {k: v for k, v in dataclasses.asdict(types.get(name, TypeParams())).items() if v is not None}
        _check_keys(src, f"filter.types.{name}.", row, {f.name for f, _ in iter_params(TypeParams)})
        types[name] = _params(src, f"filter.types.{name}", TypeParams, {**base, **row})
    return dataclasses.replace(filt, types=types)


def _material(src: str, key: str, v: Any) -> str:
    return _str(src, key, v, MATERIALS)


def scenario_from_dict(data: dict[str, Any], source: str = "<memory>",
                       seed_override: int | None = None) -> Scenario:
    """Build and validate a :class:`Scenario` from a parsed TOML/JSON dict.

    Scatterers may give ``z_range = [lo, hi]`` instead of a z coordinate (``position = [x, y]``):
    z is then drawn once, uniformly, from ``numpy.random.default_rng(seed)`` in file order.
    """
    src = source
    if not isinstance(data, dict):
        raise ConfigError(f"{src}: expected a TOML table at top level")
    _check_keys(src, "", data, _TOP_KEYS)
    for req in ("name", "bs"):
        if req not in data:
            raise _err(src, req, "required key is missing")
    if "vehicles" not in data and "n_vehicles" not in data:
        raise _err(src, "vehicles", "required key is missing (or give n_vehicles = N with an xml_scene)")
    name = _name(src, "name", data["name"])
    seed = _num(src, "seed", data.get("seed", 0), **_b("seed"))
    if seed_override is not None:
        seed = seed_override
    rng = np.random.default_rng(seed)
    bs = _vec(src, "bs", data["bs"], 3, **_b("bs"))
    dt = _num(src, "dt", data.get("dt", 0.5), **_b("dt"))
    steps = _num(src, "steps", data.get("steps", 40), **_b("steps"))
    freq = _num(src, "frequency_hz", data.get("frequency_hz", 28e9), **_b("frequency_hz"))
    xml_scene = data.get("xml_scene")
    if xml_scene is not None:
        xml_scene = _str(src, "xml_scene", xml_scene)

    buildings = []
    raw_b = data.get("buildings", [])
    if not isinstance(raw_b, list):
        raise _err(src, "buildings", "expected an array of tables [[buildings]]")
    for i, b in enumerate(raw_b):
        w = f"buildings[{i}]."
        if not isinstance(b, dict):
            raise _err(src, f"buildings[{i}]", "expected a table")
        _check_keys(src, w, b, {"name", "min", "max", "material"})
        for req in ("name", "min", "max"):
            if req not in b:
                raise _err(src, w + req, "required key is missing")
        lo = _vec(src, w + "min", b["min"], 3, **_b("buildings[].min"))
        hi = _vec(src, w + "max", b["max"], 3, **_b("buildings[].max"))
        if any(h <= l for l, h in zip(lo, hi)):
            raise _err(src, w + "max", f"expected max > min on every axis, got min={list(lo)} max={list(hi)}")
        buildings.append(Building(_name(src, w + "name", b["name"]), lo, hi,
                                  _material(src, w + "material", b.get("material", "concrete"))))

    scatterers = []
    raw_s = data.get("scatterers", [])
    if not isinstance(raw_s, list):
        raise _err(src, "scatterers", "expected an array of tables [[scatterers]]")
    for i, s in enumerate(raw_s):
        w = f"scatterers[{i}]."
        if not isinstance(s, dict):
            raise _err(src, f"scatterers[{i}]", "expected a table")
        _check_keys(src, w, s, {"name", "position", "z_range", "size", "shape", "material",
                                "scattering_coefficient"})
        for req in ("name", "position"):
            if req not in s:
                raise _err(src, w + req, "required key is missing")
        if "z_range" in s:
            xy = _vec(src, w + "position", s["position"], 2, **_b("scatterers[].position"))
            zr = _vec(src, w + "z_range", s["z_range"], 2, **_b("scatterers[].z_range"))
            if zr[1] < zr[0]:
                raise _err(src, w + "z_range", f"expected [lo, hi] with lo <= hi, got {list(zr)}")
            pos = (xy[0], xy[1], float(rng.uniform(zr[0], zr[1])))
        else:
            pos = _vec(src, w + "position", s["position"], 3, **_b("scatterers[].position"))
        scatterers.append(Scatterer(
            _name(src, w + "name", s["name"]), pos,
            _num(src, w + "size", s.get("size", 1.0), **_b("scatterers[].size")),
            _str(src, w + "shape", s.get("shape", "box"), ("box", "cylinder")),
            _material(src, w + "material", s.get("material", "metal")),
            _num(src, w + "scattering_coefficient", s.get("scattering_coefficient", 0.7),
                 **_b("scatterers[].scattering_coefficient"))))

    ground = None
    if "ground" in data:
        g = data["ground"]
        if not isinstance(g, dict):
            raise _err(src, "ground", "expected a table")
        _check_keys(src, "ground.", g, {"z", "extent", "material"})
        ground = Ground(_num(src, "ground.z", g.get("z", 0.0), **_b("ground.z")),
                        _num(src, "ground.extent", g.get("extent", 400.0), **_b("ground.extent")),
                        _material(src, "ground.material", g.get("material", "concrete")))

    vehicles = []
    raw_v = data.get("vehicles", [])
    if not isinstance(raw_v, list):
        raise _err(src, "vehicles", "expected an array of tables [[vehicles]]")
    if "n_vehicles" in data or any(isinstance(v, dict) and "route" in v for v in raw_v):
        raw_v = _street_vehicles(src, data, raw_v, bs, dt, steps, seed)
    if not raw_v:
        raise _err(src, "vehicles", "expected at least one [[vehicles]] entry; a scene needs a receiver")
    vkeys = {f.name for f in dataclasses.fields(Vehicle)}
    for i, v in enumerate(raw_v):
        w = f"vehicles[{i}]."
        if not isinstance(v, dict):
            raise _err(src, f"vehicles[{i}]", "expected a table")
        _check_keys(src, w, v, vkeys)
        for req in ("name", "initial_state"):
            if req not in v:
                raise _err(src, w + req, "required key is missing")
        st = _vec(src, w + "initial_state", v["initial_state"], 7)
        for j, k in ((0, "0:3"), (1, "0:3"), (2, "0:3"), (3, "3"), (4, "4"), (5, "5"), (6, "6")):
            _num(src, f"{w}initial_state[{j}]", st[j], **_b(f"vehicles[].initial_state[{k}]"))
        motion = _str(src, w + "motion", v.get("motion", "ct"), ("ct", "waypoints"))
        wps: tuple[tuple[float, float], ...] = ()
        if motion == "waypoints":
            raw_w = v.get("waypoints")
            if not isinstance(raw_w, list) or len(raw_w) < 2:
                raise _err(src, w + "waypoints", "expected at least two [x, y] points for motion = 'waypoints'")
            wps = tuple(_vec(src, f"{w}waypoints[{j}]", p, (2, 3), **_b("vehicles[].waypoints")) for j, p in enumerate(raw_w))  # type: ignore[misc]
            if len({len(p) for p in wps}) != 1:
                raise _err(src, w + "waypoints", "expected all [x, y] or all [x, y, z] points, not a mix")
            if st[4] <= 0:
                raise _err(src, w + "initial_state[4]", "expected speed > 0 for motion = 'waypoints'")
            if abs(st[0] - wps[0][0]) > 1e-6 or abs(st[1] - wps[0][1]) > 1e-6:
                raise _err(src, w + "initial_state", f"expected x, y equal to the first waypoint "
                           f"{list(wps[0])} for motion = 'waypoints', got {list(st[:2])}")
        elif "waypoints" in v:
            raise _err(src, w + "waypoints", "only allowed with motion = 'waypoints'")
        veh = Vehicle(
            _name(src, w + "name", v["name"]), st, motion, wps,
            _num(src, w + "length", v.get("length", 4.5), **_b("vehicles[].length")),
            _num(src, w + "width", v.get("width", 1.8), **_b("vehicles[].width")),
            _num(src, w + "height", v.get("height", 1.5), **_b("vehicles[].height")),
            _num(src, w + "roof_gap", v.get("roof_gap", 0.05), **_b("vehicles[].roof_gap")),
            _material(src, w + "material", v.get("material", "metal")),
            _num(src, w + "scattering_coefficient", v.get("scattering_coefficient", 0.5),
                 **_b("vehicles[].scattering_coefficient")))
        start = wps[0] if wps else st[:2]
        for b in buildings:
            if b.min[0] < start[0] < b.max[0] and b.min[1] < start[1] < b.max[1] and b.min[2] < st[2] < b.max[2] + 1e-9:
                raise _err(src, w + "initial_state", f"vehicle '{veh.name}' starts inside building "
                           f"'{b.name}'; move it outside [{list(b.min)}, {list(b.max)}]")
        vehicles.append(veh)

    names = [o.name for o in (*buildings, *scatterers, *vehicles)]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise _err(src, "name", f"object names must be unique; duplicated: {dup}")

    sensor = _params(src, "sensor", SensorParams, data.get("sensor"))
    filt = _filter_params(src, data.get("filter"))
    if filt.pd_model == "beta":  # the Beta prior's mean is the p_detect of the types that learn it (VA, SP)
        for t in ("VA", "SP"):
            if not 0.0 < filt.type_params(t).p_detect < 1.0:
                raise _err(src, f"filter.types.{t}.p_detect", f"pd_model = \"beta\" needs 0 < p_detect < 1 (the "
                           f"mean of the Beta prior), got {filt.type_params(t).p_detect}")
    fusion = _params(src, "fusion", FusionParams, data.get("fusion"))
    if not (isinstance(data.get("fusion"), dict) and "start" in data["fusion"]):
        # default schedule: vehicle i first talks to the BS at step 5 + i (paper: 5 and 6)
        fusion = dataclasses.replace(fusion, start=tuple(5 + i for i in range(len(vehicles))))
    if len(fusion.start) not in (1, len(vehicles)):
        raise _err(src, "fusion.start", f"expected 1 or {len(vehicles)} start steps (one per vehicle), "
                   f"got {len(fusion.start)}")
    ev = _params(src, "evaluation", EvalParams, data.get("evaluation"))
    return Scenario(name=name, bs=bs, vehicles=tuple(vehicles), buildings=tuple(buildings),
                    scatterers=tuple(scatterers), ground=ground, dt=dt, steps=steps,
                    frequency_hz=freq, seed=seed, xml_scene=xml_scene, sensor=sensor, filter=filt,
                    fusion=fusion, evaluation=ev, source_file=src)


def _street_vehicles(src: str, data: dict[str, Any], raw_v: list, bs: tuple[float, ...], dt: float, steps: int,
                     seed: int) -> list:
    """Vehicles with ``route = [[x, y], ...]`` and ``n_vehicles = N`` -> plain waypoint vehicles on the streets.

    Route points are snapped to the street centrelines of the ``xml_scene`` and joined along the
    streets (:func:`mmslam.scenes.streets.plan_route`); ``n_vehicles`` adds N cars ``car_000``...
    on seeded random routes near the BS (:func:`mmslam.scenes.streets.random_routes`; speeds
    U(4, 8) m/s from ``numpy.random.default_rng([seed, 0x5354])``; each car stays >= 6 m from the
    earlier random cars at every step). Waypoints are 3-D: the antenna (``antenna_height`` m,
    default 1.6) follows the terrain. Routed cars that overlap each other are refused when the
    trace starts (:func:`mmslam.scenes.geometry.check_vehicle_overlaps`).
    """
    if not data.get("xml_scene"):
        raise _err(src, "n_vehicles" if "n_vehicles" in data else "vehicles.route",
                   "street routes need an xml_scene (an external city scene); give waypoints instead")
    n_rand = 0
    if "n_vehicles" in data:
        n_rand = int(_num(src, "n_vehicles", data["n_vehicles"], **_b("n_vehicles")))
    from mmslam.scenes.streets import scenario_street_context

    ctx = scenario_street_context(src, data, bs)
    out = []
    for i, v in enumerate(raw_v):
        if not isinstance(v, dict) or "route" not in v:
            out.append(v)
            continue
        w = f"vehicles[{i}]."
        _check_keys(src, w, v, _ROUTE_KEYS)
        if "name" not in v:
            raise _err(src, w + "name", "required key is missing")
        pts = v["route"]
        if not isinstance(pts, list) or len(pts) < 2:
            raise _err(src, w + "route", "expected at least two [x, y] points")
        xy = np.array([_vec(src, f"{w}route[{j}]", p, 2) for j, p in enumerate(pts)])
        speed = _num(src, w + "speed", v.get("speed", 6.0), **_b("vehicles[].speed"))
        ah = _num(src, w + "antenna_height", v.get("antenna_height", 1.6), **_b("vehicles[].antenna_height"))
        bias = _num(src, w + "clock_bias", v.get("clock_bias", 0.0), **_b("vehicles[].clock_bias"))
        x0, x1, y0, y1 = ctx.sm.extent
        for j, (x, y) in enumerate(xy):
            if not (x0 <= x <= x1 and y0 <= y <= y1):  # would be snapped to a far street without a word
                raise _err(src, f"{w}route[{j}]", f"[{x:g}, {y:g}] is outside the street map of the xml_scene "
                           f"(x {x0:.0f}..{x1:.0f} m, y {y0:.0f}..{y1:.0f} m); choose a point inside it "
                           "(points inside are snapped to the nearest street)")
        try:
            wp = ctx.route(xy, ah)
        except ConfigError as e:  # no street path between two of its points: name the file and the key
            raise _err(src, w + "route", str(e)) from None
        if len(wp) < 2:  # every point snapped to one street cell: no route to drive
            raise _err(src, w + "route", "its points all snap to one place on the streets; give points along a "
                       "street, farther apart (mmslam scene streets draws them)")
        rest = {k: v[k] for k in v if k not in ("route", "speed", "clock_bias", "antenna_height")}
        out.append(_waypoint_vehicle(rest, wp, speed, bias))
    if n_rand:
        rng = np.random.default_rng([seed, 0x5354])
        speeds = rng.uniform(4.0, 8.0, n_rand)
        routes = ctx.random(n_rand, speeds * dt * steps, rng, steps)  # clear of each other
        taken = {v.get("name") for v in out if isinstance(v, dict)}
        for k, (wp, sp) in enumerate(zip(routes, speeds)):
            name = f"car_{k:03d}"
            if name in taken:
                raise _err(src, "n_vehicles", f"vehicle name '{name}' is taken; rename that vehicle")
            out.append(_waypoint_vehicle({"name": name}, wp, float(sp), 100.0 * (k + 1)))
    return out


def _waypoint_vehicle(base: dict, wp: np.ndarray, speed: float, bias: float) -> dict:
    d = wp[1, :2] - wp[0, :2]
    heading = float(np.arctan2(d[1], d[0]))
    return {**base, "motion": "waypoints", "waypoints": [[float(a) for a in p] for p in wp],
            "initial_state": [float(wp[0, 0]), float(wp[0, 1]), float(wp[0, 2]), heading, float(speed), 0.0, bias]}


def dict_from_resolved(d: dict[str, Any]) -> dict[str, Any]:
    """Turn :meth:`Scenario.to_dict` output back into loader input (no random draws left)."""
    d = json.loads(json.dumps(d))
    if d.get("ground") is None:
        d.pop("ground", None)
    if d.get("xml_scene") is None:
        d.pop("xml_scene", None)
    for v in d["vehicles"]:
        if v.get("motion") != "waypoints":
            v.pop("waypoints", None)
    return d


def scenario_from_resolved(d: dict[str, Any], source: str = "the stored scenario") -> Scenario:
    """Inverse of :meth:`Scenario.to_dict` (used to read the scenario back from a cache).

    ``source``: the file it came from, named in error messages (give the manifest's path)."""
    return scenario_from_dict(dict_from_resolved(d), source)


PARAM_SECTIONS: dict[str, type] = {"sensor": SensorParams, "filter": FilterParams,
                                   "fusion": FusionParams, "evaluation": EvalParams}
"""Scenario sections made of declared parameters (see :mod:`mmslam.scenes.params`)."""


def with_overrides(scn: Scenario, sets: list[str] | tuple[str, ...]) -> Scenario:
    """``scn`` with ``section.key=value`` overrides applied and validated like the TOML file.

    ``sets`` are strings such as ``"filter.merge=4"`` or ``"fusion.beta_inside_fov=0.5"``
    (values read as TOML). Raises a one-line :class:`~mmslam.errors.ConfigError` naming the key.
    """
    if not sets:
        return scn
    d = dict_from_resolved(scn.to_dict())
    for text in sets:
        try:
            key, value = parse_override(text)
        except ValueError as e:
            raise ConfigError(str(e)) from None
        section, _, name = key.partition(".")
        if section == "filter" and name in TYPE_PARAM_ALIASES:  # an old flat key: its table entry
            t, k = TYPE_PARAM_ALIASES[name]
            if k == "merge" and isinstance(value, (int, float)) and not isinstance(value, bool) and value < 0:
                value = -1.0  # merge_va < 0: the old "same as filter.merge"
            name = f"types.{t}.{k}"
        if section == "filter" and name.startswith("types."):
            _, t, k = (name.split(".", 2) + ["", ""])[:3]
            if not t or k not in {f.name for f, _ in iter_params(TypeParams)}:
                names = [f.name for f, _ in iter_params(TypeParams)]
                near = did_you_mean(k, names) if t else None
                if near is not None:
                    raise ConfigError(f"--set {key}: unknown parameter; did you mean filter.types.{t}.{near}?")
                raise ConfigError(f"--set {key}: expected filter.types.<TYPE>.<key> with key one of "
                                  f"{', '.join(names)} (see docs/scenario.md)")
            d.setdefault("filter", {}).setdefault("types", {}).setdefault(t, {})[k] = value
            continue
        cls = PARAM_SECTIONS.get(section)
        names = [f.name for f, _ in iter_params(cls)] if cls is not None else []
        if name not in names:
            known = [f"{s}.{f.name}" for s, c in PARAM_SECTIONS.items() for f, _ in iter_params(c)]
            near = did_you_mean(key, known + [f"filter.{a}" for a in TYPE_PARAM_ALIASES])
            if near is not None:
                raise ConfigError(f"--set {key}: unknown parameter; did you mean {near}? (all: docs/scenario.md)")
            raise ConfigError(f"--set {key}: unknown parameter; expected section.key with one of "
                              f"{', '.join(known)} (see docs/scenario.md)")
        d.setdefault(section, {})[name] = value
    out = scenario_from_dict(d, "--set")  # errors name the option: "--set: key 'filter.merge': ..."
    if any(parse_override(t)[0] == "fusion.start" for t in sets):
        check_fusion_start(out, "--set", key="fusion.start")
    return out


def _cell(text: str) -> str:
    """Text safe inside a Markdown table cell (``|`` escaped)."""
    return text.replace("|", "\\|")


SCENARIO_DOC = "docs/scenario.md"
"""The scenario reference in the repository, generated by :func:`scenario_reference` (a test keeps it current)."""


def parameter_reference() -> str:
    """Markdown tables of every declared parameter (key, default, unit, bounds, meaning)."""
    out = []
    for section, cls in PARAM_SECTIONS.items():
        out.append(f"### [{section}]\n\n{(cls.__doc__ or '').strip().splitlines()[0]}\n")
        out.append("| key | default | unit | bounds | meaning |\n|---|---|---|---|---|")
        out.extend(f"| `{k}` | {d} | {u} | {_cell(b)} | {_cell(doc)} |" for k, d, u, b, doc in param_rows(cls, section))
        out.append("")
        if cls is FilterParams:
            rows = ", ".join(f"{n} (" + ", ".join(f"{k} {str(v).lower()}" if isinstance(v, bool) else
                                                  f"{k} {v:g}" if isinstance(v, float) else f"{k} {v}"
                                                  for k, v in dataclasses.asdict(r).items()
                                                  if v is not None) + ")" for n, r in DEFAULT_TYPE_PARAMS.items())
            aliases = ", ".join(f"`{a}`" for a in TYPE_PARAM_ALIASES)
            out.append(f"#### [filter.types.<TYPE>]\n\nThe filter's parameters of each landmark type, one row per type "
                       f"(`BS`, `VA`, `SP`, `VS`, or a registered one), e.g. `[filter.types.VA]` with `merge = 4`; "
                       f"a row sets only the keys it gives over the built-in rows {rows}. The old flat keys "
                       f"{aliases} are aliases (`merge_va` < 0: not set).\n")
            out.append("| key | default | unit | bounds | meaning |\n|---|---|---|---|---|")
            out.extend(f"| `{k}` | {d} | {u} | {_cell(b)} | {_cell(doc)} |"
                       for k, d, u, b, doc in param_rows(TypeParams, "filter.types.<TYPE>"))
            out.append("")
    return "\n".join(out)


def load_scenario(path: str | Path, seed_override: int | None = None) -> Scenario:
    """Load and validate a scenario TOML file."""
    p = Path(path)
    if not p.is_file():
        raise ConfigError(f"{p}: scenario file not found; give a preset name ({', '.join(list_presets())}) "
                          "or an existing .toml file")
    try:
        data = tomllib.loads(p.read_text(encoding="utf-8"))
    except UnicodeDecodeError as e:
        raise ConfigError(f"{p}: not UTF-8 text (byte {e.start}: {e.object[e.start:e.start + 1]!r}); a scenario "
                          "file is TOML, saved as UTF-8") from None
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"{p}: not valid TOML ({e}); fix the syntax") from None
    except RecursionError:  # tomllib recurses once per nesting level: thousands of [ ] exhaust the stack
        raise ConfigError(f"{p}: arrays or tables nested too deeply for a scenario file (a scenario nests at "
                          "most three levels, e.g. buildings[].vertices[][]); fix the file") from None
    scn = scenario_from_dict(data, str(p), seed_override)
    if isinstance(data.get("fusion"), dict) and "start" in data["fusion"]:
        check_fusion_start(scn, str(p))
    return scn


def check_fusion_start(scn: Scenario, source: str, steps: int | None = None, key: str = "fusion.start") -> None:
    """Refuse (one line) a fusion schedule whose first upload ``min(fusion.start)`` is not before the last step.

    The GOSPA / RMSE tables cover steps ``>= min(fusion.start)``: such a run would evaluate nothing
    (an empty table). ``steps``: the run length (default ``scn.steps``). Checked where the user gives
    the schedule (a scenario file, ``--set fusion.start``), not on a cache traced with fewer ``--steps``.
    """
    n = scn.steps if steps is None else int(steps)
    first = min(scn.fusion.start)
    if first >= n:
        raise ConfigError(f"{source}: key '{key}': first fusion step {first} is not before the last step {n - 1} "
                          f"(steps = {n}), so nothing would be fused or evaluated; expected a start step below {n}")


def list_presets() -> list[str]:
    """Names of the scenario presets shipped with the package."""
    root = resources.files("mmslam.scenes") / "presets"
    return sorted(f.name[:-5] for f in root.iterdir() if f.name.endswith(".toml"))


def preset_path(name: str) -> Path:
    root = resources.files("mmslam.scenes") / "presets"
    return Path(str(root / f"{name}.toml"))


def load_preset(name: str) -> Scenario:
    """Load a shipped preset by name (``paper``, ``street``, ...)."""
    if name not in list_presets():
        raise ConfigError(f"unknown scenario '{name}'; expected a preset ({', '.join(list_presets())}) "
                          "or a path to a .toml file")
    s = load_scenario(preset_path(name))
    return dataclasses.replace(s, source_file=f"preset:{name}")


def resolve_scenario(spec: str | Path | Scenario) -> Scenario:
    """A preset name, a TOML path or a Scenario -> Scenario."""
    if isinstance(spec, Scenario):
        return spec
    s = str(spec)
    if s.endswith(".toml") or Path(s).is_file():
        return load_scenario(s)
    return load_preset(s)


def scenario_reference() -> str:
    """The full scenario-file reference (Markdown): every key, its default, unit, bounds and meaning.

    Written to :data:`SCENARIO_DOC` by ``mmslam scene reference > docs/scenario.md``.
    """
    head = ("# Scenario file reference\n\n"
            "Generated from the code (`mmslam scene reference > docs/scenario.md`); a test fails when "
            "it is out of date. A scenario is a UTF-8 TOML file; every key below is checked when the file is "
            "loaded, and a value outside its bounds is refused with one line naming the file and the key "
            "(exit code 2). Bounds are inclusive; `(` / `)` mark an open end. Frames: x east, y north, z up; "
            "angles in radians. `[[buildings]]`, `[[scatterers]]` and `[[vehicles]]` are arrays of tables "
            "(`buildings[].min` is the key `min` of each `[[buildings]]` entry). The `[sensor]`, `[filter]`, "
            "`[fusion]` and `[evaluation]` keys can also be set per run with "
            "`mmslam slam --set section.key=value` or `mmslam ablate --set section.key=value`.\n\n"
            "## Geometry and time\n\n"
            "| key | default | unit | bounds | meaning |\n|---|---|---|---|---|")
    rows = [f"| `{k}` | {d} | {s.unit or '-'} | {_cell(s.bounds_text()) if s.choices or s.lo is not None or s.hi is not None else '-'}"
            f" | {_cell(s.doc)} |" for k, (d, s) in GEOMETRY.items()]
    return "\n".join([head, *rows, "", "## Parameters", "", parameter_reference()]).rstrip() + "\n"



# ====================================================================== settings of a stored scenario
GEOMETRY_SENSOR_KEYS: tuple[str, ...] = ("fov_range", "vehicle_noise_std", "true_process_noise")
"""``[sensor]`` keys that shape the traced paths or the truth (:meth:`Scenario.geometry_hash`): a stored
scenario always keeps them."""


def default_settings() -> dict[str, Any]:
    """This mmslam's defaults of every parameter section, in :meth:`Scenario.to_dict`'s form."""
    return json.loads(json.dumps({s: dataclasses.asdict(cls()) for s, cls in PARAM_SECTIONS.items()}))


def _scenario_file_data(scn: Scenario) -> dict[str, Any] | None:
    """The TOML data of ``scn``'s own file as written (a preset's or a TOML file's), or None when ``scn`` did not
    come from a readable file (built in memory)."""
    src = scn.source_file or ""
    if src.startswith("preset:"):
        path = preset_path(src[len("preset:"):])
    elif src and not src.startswith("<"):
        path = Path(src)
    else:
        return None
    try:
        return tomllib.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError, RecursionError):
        return None


def settings_diff(old: dict[str, Any], new: dict[str, Any]) -> list[str]:
    """``"section.key: old -> new"`` for each run parameter (``seed`` and :data:`PARAM_SECTIONS`, nested keys
    dotted) on which two resolved scenarios (:meth:`~mmslam.scenes.scenario.Scenario.to_dict`) differ; a key only one
    of them has (a parameter added or removed between the versions that wrote them) is left out."""
    def flat(d: Any, prefix: str) -> dict[str, Any]:
        if not isinstance(d, dict):
            return {prefix: d}
        out: dict[str, Any] = {}
        for k, v in d.items():
            out.update(flat(v, f"{prefix}.{k}"))
        return out

    a = {**flat(old.get("seed"), "seed"), **{k: v for s in PARAM_SECTIONS for k, v in flat(old.get(s, {}), s).items()}}
    b = {**flat(new.get("seed"), "seed"), **{k: v for s in PARAM_SECTIONS for k, v in flat(new.get(s, {}), s).items()}}
    # a key on one side only is a parameter one of the two versions does not have: not comparable
    return [f"{k}: {a[k]} -> {b[k]}" for k in sorted(set(a) & set(b)) if a[k] != b[k]]


def scenario_settings(scn: Scenario) -> dict[str, Any] | None:
    """The parameter tables (``[sensor]``, ``[filter]``, ``[fusion]``, ``[evaluation]``) as ``scn``'s own
    file writes them (a preset's or a TOML file's; only the keys it sets), or None when ``scn`` did not
    come from a readable file (built in memory)."""
    data = _scenario_file_data(scn)
    if data is None:
        return None
    return json.loads(json.dumps({s: data[s] for s in PARAM_SECTIONS if isinstance(data.get(s), dict)}, default=str))


def scenario_route_points(scn: Scenario) -> dict[str, np.ndarray]:
    """Vehicle name -> the ``route`` points ``(k, 2)`` (m) of ``scn``'s own file as written, before they are snapped
    to the streets (:func:`mmslam.scenes.trajectory.route_warnings`); empty without a readable file or routes."""
    data = _scenario_file_data(scn) or {}
    vehicles = data.get("vehicles", [])
    return {str(v["name"]): np.asarray(v["route"], float) for v in (vehicles if isinstance(vehicles, list) else [])
            if isinstance(v, dict) and "name" in v and isinstance(v.get("route"), list)}


def _explicit_keys(tables: dict[str, Any]) -> dict[str, set[str]]:
    """Dotted keys (:meth:`Scenario.to_dict`'s names, e.g. ``types.VA.p_detect``) each section of a file sets."""
    out: dict[str, set[str]] = {}
    for s, t in tables.items():
        keys: set[str] = set()
        for k, v in (t.items() if isinstance(t, dict) else ()):
            if s == "filter" and k == "types" and isinstance(v, dict):
                keys |= {f"types.{ty}.{kk}" for ty, row in v.items() if isinstance(row, dict) for kk in row}
            elif s == "filter" and k in TYPE_PARAM_ALIASES:
                ty, kk = TYPE_PARAM_ALIASES[k]
                keys.add(f"types.{ty}.{kk}")
            else:
                keys.add(k)
        out[s] = keys
    return out


def _flat(d: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_flat(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


def _unflat(f: dict[str, Any]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in f.items():
        *head, last = k.split(".")
        node = out
        for h in head:
            node = node.setdefault(h, {})
        node[last] = v
    return out


def preset_additions(settings: dict[str, Any] | None, name: str | None, geometry: str) -> dict[str, Any] | None:
    """The recorded parameter tables ``settings`` of a cache whose scenario was the shipped preset ``name``, with
    the keys that preset has set since (e.g. a parameter added to pin a published configuration): the preset's
    current tables if the cache's scenario has the preset's geometry (``geometry``: its
    :meth:`Scenario.geometry_hash`) and every recorded key has the preset's current value (the same preset,
    less additions); else ``settings`` unchanged (another file of that name, or a preset edited since)."""
    if not isinstance(settings, dict) or name not in list_presets():
        return settings
    preset = load_preset(name)
    if preset.geometry_hash() != geometry:
        return settings
    now = scenario_settings(preset) or {}
    rec = {(sec, k): v for sec, t in settings.items() if isinstance(t, dict) for k, v in _flat(t).items()}
    cur = {(sec, k): v for sec, t in now.items() for k, v in _flat(t).items()}
    return now if all(cur.get(k, rec) == v for k, v in rec.items()) else settings


def refresh_settings(resolved: dict[str, Any], settings: dict[str, Any] | None, trace_defaults: dict[str, Any] | None,
                     source: str = "the stored scenario", preset: str | None = None) -> tuple[Scenario, list[str]]:
    """A stored (cached) scenario with this mmslam's defaults where its scenario left a parameter open.

    A cache stores the resolved scenario: every parameter, defaults included, as the mmslam that traced
    it had them. Read back literally, a newer mmslam would run an old cache with old defaults. Here each
    parameter of the ``[sensor]``, ``[filter]``, ``[fusion]`` and ``[evaluation]`` sections is taken

    - as stored, if the scenario's file set it (``settings``, :func:`scenario_settings` at trace time), if
      it is a trace parameter (:data:`GEOMETRY_SENSOR_KEYS`), or if the stored value differs from that
      mmslam's default (an override made in memory);
    - else (the stored value is the old default) as this mmslam's default.

    Args:
        resolved: the stored :meth:`Scenario.to_dict`.
        settings: the scenario file's own tables at trace time (None: none recorded, e.g. built in memory).
        trace_defaults: :func:`default_settings` of the mmslam that traced it (None: not recorded: the
            stored scenario is returned unchanged).
        preset: the stored scenario's name; if it was that shipped preset, the keys the preset has set since
            take the preset's values (:func:`preset_additions`): a published configuration stays pinned.

    Returns:
        ``(scenario, changed)``: ``changed`` lists ``"section.key: old -> new"`` for each parameter that now
        differs from the stored one. The geometry never changes (checked by its hash; the stored scenario
        is returned if it would).
    """
    base = scenario_from_resolved(resolved, source)
    if not (isinstance(trace_defaults, dict) and all(isinstance(trace_defaults.get(s, {}), dict)
                                                     for s in PARAM_SECTIONS)):
        return base, []  # not recorded (or not as this mmslam writes it): the stored scenario as it is
    settings = preset_additions(settings, preset, base.geometry_hash())
    tables = {k: v for k, v in settings.items() if isinstance(v, dict)} if isinstance(settings, dict) else {}
    explicit = _explicit_keys(tables)
    now = default_settings()
    data = dict_from_resolved(resolved)
    changed: list[str] = []
    missing = object()
    for s in PARAM_SECTIONS:
        stored, then = _flat(resolved.get(s) or {}), _flat(trace_defaults.get(s) or {})
        out = dict(stored)
        own = _flat(tables.get(s, {}))
        for k, v in _flat(now[s]).items():
            if k in explicit.get(s, ()) and k not in stored and k in own:  # set by its file, unknown when traced
                out[k] = own[k]
                changed.append(f"{s}.{k}: (none) -> {json.dumps(own[k])}")
                continue
            if k in explicit.get(s, ()) or (s == "sensor" and k in GEOMETRY_SENSOR_KEYS):
                continue
            old = stored.get(k, missing)
            if old is missing or (k in then and old == then[k]):
                out[k] = v
                if old is not missing and old != v:
                    changed.append(f"{s}.{k}: {json.dumps(old)} -> {json.dumps(v)}")
        data[s] = _unflat(out)
    scn = scenario_from_dict(data, source)
    if scn.geometry_hash() != base.geometry_hash():
        return base, []
    return dataclasses.replace(scn, source_file=base.source_file), changed
