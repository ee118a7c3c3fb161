"""Sensor model: noise-free traced paths -> measurement sets of one Monte Carlo run (docs/design.md sections 1, 4, 5).

Ray tracing is noise-free and cached; everything random about the measurements happens here,
drawn from a caller-supplied :class:`numpy.random.Generator`:

- the true clock bias ``B_k`` (random walk, metres);
- per path: detection with ``p_detect`` (SP / VS only within ``fov_range`` of the true vehicle
  position; BS / VA always in the FOV) and additive Gaussian noise ``N(0, R)``;
- per vehicle and step: ``Poisson(clutter_mean)`` clutter, uniform over the measurement space;
- the order of each measurement set (shuffled: the filter must not rely on it).

A measurement is ``z = [TOA + B, AOD az, AOD el, AOA az - heading, AOA el]`` (m, rad; azimuths
wrapped to ``(-pi, pi]``), see :mod:`mmslam.slam.models.measurement`.

Two detection / noise models:

- **constant** (default; the paper's): ``p_D = sensor.p_detect``, noise ``R = diag(toa_std^2,
  angle_std^2 x 4)`` for every path;
- **power-aware** (``sensor.model = "link"``, or ``link=LinkBudget(...)``): from each path's
  ``power_db`` (the traced path gain) the link budget gives its SNR, the SNR gives the detection probability (envelope detector at a
  fixed false-alarm rate, Marcum Q) and the measurement standard deviations (Cramer-Rao bounds of
  delay and angles: std proportional to ``1 / sqrt(SNR)``, inversely to the bandwidth / array
  size). Each measurement carries its own covariance (:attr:`Measurements.R_meas`); clutter
  slots carry the covariance at the detection threshold SNR. See :class:`LinkBudget`.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Sequence

import numba as nb
import numpy as np

from mmslam.errors import MmslamError
from mmslam.scenes.scenario import Scenario, SensorParams

from ..models.dynamics import wrap_angle
from ..specs.landmarks import is_range_gated, known_codes, landmark_types
from ..models.measurement import MEAS_DIM, OTHER

SPEED_OF_LIGHT = 299_792_458.0  # m/s
BOLTZMANN_DBM_HZ = -173.975  # 10 log10(k T0 / 1 mW) at T0 = 290 K, dBm/Hz

_Z_COLUMNS = ("toa_m", "aod_az", "aod_el", "aoa_az", "aoa_el")
_LM_COLUMNS = ("lm_x", "lm_y", "lm_z")


@dataclass
class Measurements:
    """Measurement sets of one Monte Carlo run, padded to ``J`` slots per (step, vehicle).

    Attributes:
        z: ``(steps, n_veh, J, 5)`` measurements ``[toa (m), aod_az, aod_el, aoa_az, aoa_el]``
            (rad; AOA azimuth in the vehicle body frame); 0 where padded.
        mask: ``(steps, n_veh, J)`` True where a slot holds a measurement.
        origin_type: ``(steps, n_veh, J)`` int8 landmark type code of the originating path
            (``BS=0 .. OTHER=4``), -1 for clutter and padding.
        origin_id: ``(steps, n_veh, J)`` object, the path's ``landmark_id``; '' for clutter / padding.
        origin_pos: ``(steps, n_veh, J, 3)`` ground-truth landmark position (global, m); NaN for
            clutter, padding and OTHER paths.
        true_states: ``(steps, n_veh, 7)`` true vehicle states ``[x, y, z, heading, speed,
            turn_rate, clock_bias]`` with the simulated clock-bias random walk.
        clutter_intensity: ``c(z) = clutter_mean / V`` with the measurement-space volume
            ``V = clutter_toa_max * 2pi * pi * 2pi * pi`` (units 1 / (m rad^4)).
        R: ``(5, 5)`` true measurement-noise covariance ``diag(toa_std^2, angle_std^2 x 4)`` (the
            constant model; with a link budget: the covariance at the detection threshold SNR).
        R_meas: ``(steps, n_veh, J, 5)`` per-measurement noise variances (diagonal of its
            covariance, m^2 and rad^2): ``diag(R)`` everywhere for the constant model, the
            path's CRB variances for the power-aware model (clutter: those at the threshold SNR);
            0 where padded.
        snr_db: ``(steps, n_veh, J)`` the path's SNR (dB) under the link budget; NaN for clutter,
            padding and the constant model.
    """

    z: np.ndarray
    mask: np.ndarray
    origin_type: np.ndarray
    origin_id: np.ndarray
    origin_pos: np.ndarray
    true_states: np.ndarray
    clutter_intensity: float
    R: np.ndarray
    R_meas: np.ndarray | None = None
    snr_db: np.ndarray | None = None

    @property
    def steps(self) -> int:
        return self.z.shape[0]

    @property
    def n_vehicles(self) -> int:
        return self.z.shape[1]

    def set(self, step: int, vehicle: int) -> np.ndarray:
        """The measurement set of one vehicle at one step, ``(J_k, 5)`` (live slots only)."""
        return self.z[step, vehicle][self.mask[step, vehicle]]

    def origin_counts(self) -> tuple[list[str], np.ndarray]:
        """How many measurements each path type gave, per step and vehicle (for evaluation only).

        Returns:
            ``(columns, counts)``: column names, the registered types then ``OTHER`` then
            ``clutter`` (false alarms: no originating path), and ``counts (steps, n_veh, len(columns))``
            int64, the live slots of each origin per (step, vehicle)."""
        codes = [s.code for s in landmark_types()] + [OTHER, -1]
        names = [s.name for s in landmark_types()] + ["OTHER", "clutter"]
        live = np.asarray(self.mask, bool)
        ot = np.asarray(self.origin_type)
        counts = np.stack([(live & (ot == c)).sum(axis=-1) for c in codes], axis=-1).astype(np.int64)
        return names, counts


def clutter_intensity(params: SensorParams) -> float:
    """Uniform clutter intensity ``clutter_mean / (toa_max * (2 pi)^2 * pi^2)`` (1 / (m rad^4))."""
    vol = params.clutter_toa_max * (2.0 * math.pi) ** 2 * math.pi**2
    if vol <= 0:
        if params.clutter_mean == 0:
            return 0.0
        raise MmslamError("sensor.clutter_toa_max must be > 0 when sensor.clutter_mean > 0")
    return params.clutter_mean / vol


def noise_covariance(params: SensorParams) -> np.ndarray:
    """True measurement-noise covariance ``diag(toa_std^2, angle_std^2 x 4)``, ``(5, 5)``."""
    return np.diag([params.toa_std**2] + [params.angle_std**2] * 4)


@dataclass(frozen=True)
class LinkBudget:
    """Power-aware sensor model: link budget, detector and Cramer-Rao accuracy (28 GHz defaults).

    SNR of a path with path gain ``G`` dB (the cache's ``power_db``): the received energy of one pilot
    OFDM symbol over the noise variance per sample, i.e. the per-sample SNR times the ``K``
    subcarriers of the symbol (``K = subcarriers``, the scenario's ``sensor.est_subcarriers``: the same
    pilots the channel estimator of ``sensor.model = "estimated"`` observes)::

        SNR_dB = tx_power_dbm + tx_gain_dbi + rx_gain_dbi + G + 10 log10(K) + processing_gain_db
                 - (-173.975 + 10 log10(bandwidth_hz) + noise_figure_db)

    Defaults: 20 dBm transmit power, an 8 x 8 BS array (18.1 dBi = 10 log10 64) and a 4 x 4
    vehicle array (12.0 dBi), 400 MHz bandwidth, 9 dB noise figure, K = 256 (24.1 dB), no further
    processing gain (one pilot symbol), false-alarm probability 1e-4 per resolution cell. A LOS path
    at 80 m (-99.5 dB) then has an SNR of about 53 dB, a wall reflection at 200 m about 37 dB, a
    2 m^2 scatterer 80 m from the BS and 30 m from the car about 16 dB. Until 2026-11-25 the
    ``10 log10(K)`` term was missing: the SNR was that of one time-domain sample, while the delay bound
    below (and ``tests/test_fidelity.py``'s numerical Fisher information) needs the energy over all
    samples; it left every SP and VS path of ``paper`` below the detection threshold (docs/estimator.md
    section 8).

    Detection probability (non-fluctuating path, envelope detector with the threshold set for
    ``pfa``): ``p_D = Q_1(sqrt(2 SNR), sqrt(-2 ln pfa))`` (Marcum Q), increasing in SNR, equal to
    ``pfa`` as the SNR goes to 0 (linear) and to 0.5 at SNR = 9.4 dB for ``pfa = 1e-4``.

    Standard deviations (Cramer-Rao bounds of one path in complex white noise, unknown complex
    gain; flat spectrum over the bandwidth ``B``, uniform half-wavelength ``N x N`` arrays,
    evaluated at broadside): ``std_toa = c sqrt(3) / (pi B sqrt(2 SNR))`` m (RMS bandwidth
    ``B / sqrt(12)``) and ``std_angle = sqrt(12 / (pi^2 (N^2 - 1) 2 SNR))`` rad with ``N = tx_array``
    for AOD and ``N = rx_array`` for AOA. ``SNR`` is the link budget's, which already holds both
    array gains (``N_t^2 N_r^2`` with ``tx_gain_dbi``, ``rx_gain_dbi`` at their defaults): the textbook
    single-tone bound ``var = 6 / (pi^2 N (N^2 - 1) SNR_el)`` of an ``N``-element line (Van Trees,
    Optimum Array Processing, ch. 8; Shahmansoori et al., IEEE TWC 2018) with the
    per-element SNR ``SNR_el = SNR / N`` (a UPA: ``N`` such lines, ``SNR_el = SNR / N^2``) is
    ``6 / (pi^2 (N^2 - 1) SNR)``; the array gain enters once. Checked against a numerical Fisher
    information of the MIMO-OFDM channel in tests/test_fidelity.py. Halving the SNR multiplies every
    std by ``sqrt(2)``.
    """

    tx_power_dbm: float = SensorParams.tx_power_dbm
    tx_gain_dbi: float = SensorParams.tx_gain_dbi
    rx_gain_dbi: float = SensorParams.rx_gain_dbi
    bandwidth_hz: float = SensorParams.bandwidth_hz
    noise_figure_db: float = SensorParams.noise_figure_db
    processing_gain_db: float = SensorParams.processing_gain_db
    pfa: float = SensorParams.pfa
    tx_array: int = SensorParams.tx_array
    rx_array: int = SensorParams.rx_array
    subcarriers: int = SensorParams.est_subcarriers

    @classmethod
    def from_sensor(cls, params: SensorParams) -> "LinkBudget":
        """The link budget of a scenario's ``[sensor]`` section (its ``tx_power_dbm`` ... ``rx_array``, and
        ``est_subcarriers`` as ``subcarriers``)."""
        names = {"subcarriers": "est_subcarriers"}
        return cls(**{f.name: getattr(params, names.get(f.name, f.name)) for f in dataclasses.fields(cls)})

    def __post_init__(self) -> None:
        for k in ("tx_power_dbm", "tx_gain_dbi", "rx_gain_dbi", "noise_figure_db", "processing_gain_db"):
            if not math.isfinite(getattr(self, k)):
                raise MmslamError(f"link budget {k}={getattr(self, k)!r}: expected a finite number (dB)")
        if not (math.isfinite(self.bandwidth_hz) and self.bandwidth_hz > 0):
            raise MmslamError(f"link budget bandwidth_hz={self.bandwidth_hz!r}: expected a positive bandwidth (Hz)")
        if not 0.0 < self.pfa < 1.0:
            raise MmslamError(f"link budget pfa={self.pfa!r}: expected a probability in (0, 1)")
        for k in ("tx_array", "rx_array"):
            if int(getattr(self, k)) < 2:
                raise MmslamError(f"link budget {k}={getattr(self, k)!r}: expected at least 2 elements per axis")
        if int(self.subcarriers) < 1:
            raise MmslamError(f"link budget subcarriers={self.subcarriers!r}: expected at least 1 subcarrier")

    @property
    def noise_dbm(self) -> float:
        """Thermal noise power over the bandwidth plus the noise figure, dBm."""
        return BOLTZMANN_DBM_HZ + 10.0 * math.log10(self.bandwidth_hz) + self.noise_figure_db

    def snr_db(self, path_gain_db: np.ndarray) -> np.ndarray:
        """SNR (dB) of paths with gains ``path_gain_db`` (dB, e.g. the cache's ``power_db``): one pilot symbol's
        energy over the noise variance per sample (class docstring)."""
        return (self.tx_power_dbm + self.tx_gain_dbi + self.rx_gain_dbi + np.asarray(path_gain_db, float)
                + 10.0 * math.log10(int(self.subcarriers)) + self.processing_gain_db - self.noise_dbm)

    def detect_prob(self, snr_db: np.ndarray) -> np.ndarray:
        """``p_D = Q_1(sqrt(2 SNR), sqrt(-2 ln pfa))`` (non-central chi-square, 2 degrees of freedom)."""
        from scipy.stats import ncx2

        snr = 10.0 ** (np.asarray(snr_db, float) / 10.0)
        return ncx2.sf(-2.0 * math.log(self.pfa), 2, 2.0 * snr)

    def threshold_snr_db(self) -> float:
        """SNR (dB) at which ``p_D = 0.5``: the typical SNR of a false alarm's covariance."""
        from scipy.optimize import brentq

        return float(brentq(lambda x: float(self.detect_prob(x)) - 0.5, -20.0, 40.0))

    def stds(self, snr_db: np.ndarray) -> np.ndarray:
        """CRB standard deviations ``(..., 5)``: ``[toa (m), aod_az, aod_el, aoa_az, aoa_el (rad)]``."""
        snr = 10.0 ** (np.asarray(snr_db, float) / 10.0)
        k = 1.0 / np.sqrt(2.0 * snr)
        toa = SPEED_OF_LIGHT * math.sqrt(3.0) / (math.pi * self.bandwidth_hz) * k

        def ang(n: int) -> float:  # the SNR holds the array gain: no further factor n (issue 23)
            return math.sqrt(12.0 / (math.pi**2 * (n * n - 1)))

        at, ar = ang(int(self.tx_array)), ang(int(self.rx_array))
        return np.stack([toa, at * k, at * k, ar * k, ar * k], axis=-1)


def fov_detect_prob(vehicle_pos: np.ndarray, lm_pos: np.ndarray, lm_type: int | np.ndarray,
                    params: SensorParams, p_inside: float | None = None) -> np.ndarray:
    """Detection probability ``p_D`` of landmarks for the filter (broadcasting over leading axes).

    Args:
        vehicle_pos: ``(..., 3)`` vehicle (antenna) positions, global frame, m.
        lm_pos: ``(..., 3)`` landmark positions (VA: image source; SP / VS: scatter point), m.
        lm_type: landmark type code(s), scalar or broadcastable to the leading shape.
        params: sensor parameters (``p_detect``, ``fov_range`` in m).
        p_inside: the value inside the FOV instead of ``params.p_detect`` (e.g. the filter's
            per-type ``p_D``); None: ``params.p_detect``.

    Returns:
        ``(...)`` float64: ``p_detect`` (or ``p_inside``) for BS / VA (always in the FOV) and for
        SP / VS within ``fov_range`` (distance <= range) of the vehicle; 0 for SP / VS beyond it.
    """
    x, u = np.asarray(lm_pos, float), np.asarray(vehicle_pos, float)
    value = float(params.p_detect if p_inside is None else p_inside)
    gated = is_range_gated(lm_type)  # the type specs' FOV rule (SP, VS: range-gated)
    if np.ndim(gated) == 0:
        if not gated:  # one type, never range-gated (BS, VA): no distances needed
            lead = x.shape[:-1] if x.shape == u.shape else np.broadcast_shapes(x.shape[:-1], u.shape[:-1])
            return np.full(lead, value)
        if x.shape[-1:] == u.shape[-1:] == (3,):  # one range-gated type: one compiled pass
            return _range_gate(u, x, float(params.fov_range), value)
    # component-wise distance: the same arithmetic as np.linalg.norm(x - u, axis=-1), without
    # NumPy's slow inner loops over the length-3 axis
    dx, dy, dz = x[..., 0] - u[..., 0], x[..., 1] - u[..., 1], x[..., 2] - u[..., 2]
    d = np.sqrt(dx * dx + dy * dy + dz * dz)
    inside = ~gated | (d <= params.fov_range)
    return np.where(inside, value, 0.0)


def _range_gate(u: np.ndarray, x: np.ndarray, fov_range: float, value: float) -> np.ndarray:
    """``value`` where ``|x - u| <= fov_range`` else 0, for ``u, x (..., 3)`` broadcast to each other.

    The leading axes are viewed as two (``(A, B, 3)``, a view for up to two leading axes) for
    :func:`_range_gate_kernel`; the result has the broadcast leading shape.
    """
    shape = x.shape
    if u.shape != shape:
        shape = np.broadcast_shapes(x.shape, u.shape)
        x, u = np.broadcast_to(x, shape), np.broadcast_to(u, shape)
    lead = shape[:-1]
    view = (1,) * (2 - len(lead)) + lead if len(lead) <= 2 else (math.prod(lead[:-1]), lead[-1])
    out = np.empty(lead)
    _range_gate_kernel(u.reshape(view + (3,)), x.reshape(view + (3,)), fov_range, value, out.reshape(view))
    return out


@nb.njit(cache=True)
def _range_gate_kernel(u: np.ndarray, x: np.ndarray, fov_range: float, value: float, out: np.ndarray) -> None:
    """``out[a, b] = value`` if ``sqrt(dx^2 + dy^2 + dz^2) <= fov_range`` else 0, ``d = x[a, b] - u[a, b]``
    (``u, x (A, B, 3)``, any strides; the arithmetic of ``np.linalg.norm(x - u, axis=-1)``)."""
    for a in range(out.shape[0]):
        for b in range(out.shape[1]):
            dx = x[a, b, 0] - u[a, b, 0]
            dy = x[a, b, 1] - u[a, b, 1]
            dz = x[a, b, 2] - u[a, b, 2]
            out[a, b] = value if math.sqrt(dx * dx + dy * dy + dz * dz) <= fov_range else 0.0


def _used_types(scn: Scenario, include_types: Sequence[int] | None) -> np.ndarray:
    if include_types is None:
        include_types = known_codes()
    types = {int(t) for t in include_types if int(t) != OTHER}
    if scn.sensor.emit_other:
        types.add(OTHER)
    return np.array(sorted(types), dtype=int)


def set_slots(s_sorted: np.ndarray, steps: int, n_veh: int) -> tuple[int, np.ndarray, np.ndarray, np.ndarray]:
    """Padding of measurement sets: ``s_sorted`` ``(n,)`` set index ``k * n_veh + v`` of each
    measurement, grouped by set (non-decreasing) -> ``(J, slot (n,), k (n,), v (n,))`` with ``J`` the
    largest set size and ``slot`` each measurement's place in its set (``Z[k, v, slot]``)."""
    per_set = np.bincount(s_sorted, minlength=steps * n_veh)
    start = np.concatenate([[0], np.cumsum(per_set)[:-1]])
    ks, vs = np.divmod(s_sorted, n_veh)
    return int(per_set.max(initial=0)), np.arange(s_sorted.size) - start[s_sorted], ks, vs


def clock_bias_walk(states: np.ndarray, std: float, rng: np.random.Generator) -> np.ndarray:
    """True states ``(steps, n_veh, 7)``: ``states`` with the clock bias (column 6, m) a random walk
    ``B_k = B_{k-1} + N(0, std^2)`` from ``B_0 = states[0, :, 6]`` (draws ``(steps - 1, n_veh)`` normals)."""
    steps, n_veh = states.shape[:2]
    inc = rng.standard_normal((max(steps - 1, 0), n_veh)) * std
    true = states.copy()
    true[:, :, 6] = states[0, :, 6][None, :] + np.concatenate([np.zeros((1, n_veh)), np.cumsum(inc, 0)])[:steps]
    return true


def odometry_readings(states: np.ndarray, std: Sequence[float], rng: np.random.Generator) -> np.ndarray:
    """The odometry a vehicle reads, ``(steps, n_veh, 2)`` speed (m/s) and turn rate (rad/s): the true inputs of
    ``states (steps, n_veh, 7)`` (columns 4 and 5) plus white Gaussian noise of ``std = (speed, turn rate)``
    (``sensor.odometry_noise_std``), drawn as one ``(steps, n_veh, 2)`` block from ``rng``; a stopped car
    (true speed 0) reads speed 0 (a wheel encoder does not creep) and no car reads a negative speed (a slow one
    reads 0 where the noise would take it below)."""
    states = np.asarray(states, dtype=float)
    out = states[..., 4:6].copy()
    out += rng.standard_normal(out.shape) * np.asarray(std, float)
    out[..., 0] = np.where(states[..., 4] == 0.0, 0.0, np.maximum(out[..., 0], 0.0))
    return out


def simulate_measurements(scn: Scenario, states: np.ndarray, paths: dict[str, np.ndarray],
                          rng: np.random.Generator,
                          include_types: Sequence[int] | None = None,
                          link: LinkBudget | None = None) -> Measurements:
    """Draw one Monte Carlo run of measurement sets from noise-free paths.

    Args:
        scn: scenario; ``scn.sensor`` gives noise, ``p_detect``, ``fov_range``, clutter and the
            clock-bias random-walk std ``vehicle_noise_std[6]`` (m per step).
        states: ``(steps, n_veh, 7)`` true vehicle states (the trajectory the paths were traced
            on); column 6 at step 0 is the initial clock bias.
        paths: ``paths`` table columns (see :mod:`mmslam.raytrace.schema`): at least ``step, rx,
            type, landmark_id, toa_m, aod_az, aod_el, aoa_az, aoa_el, lm_x, lm_y, lm_z`` (global
            frame). Rows with ``step >= steps`` or ``rx >= n_veh`` are ignored.
        rng: the only source of randomness.
        include_types: landmark type codes whose paths become measurements (None: every registered
            type, :mod:`mmslam.slam.specs.landmarks`). ``OTHER`` (4) paths are
            used if and only if ``scn.sensor.emit_other`` is set, whatever this argument says.
        link: a :class:`LinkBudget` for the power-aware model (needs ``power_db`` on every used
            row); ``None``: the scenario's ``sensor.model`` decides (``constant``: ``p_detect``,
            ``toa_std``, ``angle_std``; ``link``: :meth:`LinkBudget.from_sensor`).

    Returns:
        :class:`Measurements`.

    The true state differs from ``states`` only in the clock bias:
    ``B_0 = states[0, :, 6]``, ``B_k = B_{k-1} + N(0, vehicle_noise_std[6]^2)``. Position,
    heading etc. are taken as given because the cached paths were traced on exactly these
    positions; process noise on them (``sensor.true_process_noise``) therefore has to be put
    into the trajectory *before* tracing (``vehicle_trajectories(scn, rng=...)``), not here.

    Draw order (fixed, so one seed gives one result): clock-bias increments ``(steps - 1,
    n_veh)``; detection uniforms and ``(n_rows, 5)`` noise normals for every used path row in
    (step, rx, type, landmark_id) order (drawn whether or not the row is in the FOV); clutter
    counts ``(steps, n_veh)``; clutter uniforms ``(n_clutter, 5)``; shuffle keys.

    Raises:
        MmslamError: a used path row has NaN in a measurement column (or, for SP / VS, in the
            landmark position), naming the column and step; or shapes do not fit.
    """
    sp = scn.sensor
    states = np.asarray(states, dtype=float)
    if states.ndim != 3 or states.shape[-1] != 7:
        raise MmslamError(f"states must have shape (steps, n_vehicles, 7), got {states.shape}")
    if not np.all(np.isfinite(states)):
        raise MmslamError("true vehicle states contain NaN or inf; check the trajectory")
    steps, n_veh, _ = states.shape
    for col in ("step", "rx", "type", "landmark_id", *_Z_COLUMNS, *_LM_COLUMNS):
        if col not in paths:
            raise MmslamError(f"paths table has no column '{col}'; the cache is not of the expected schema")

    true = clock_bias_walk(states, sp.vehicle_noise_std[6], rng)

    # ---- select and order the used path rows
    step = np.asarray(paths["step"]).astype(int)
    rx = np.asarray(paths["rx"]).astype(int)
    typ = np.asarray(paths["type"]).astype(int)
    ids = np.asarray(paths["landmark_id"]).astype(str)
    sel = (step >= 0) & (step < steps) & (rx >= 0) & (rx < n_veh) & np.isin(typ, _used_types(scn, include_types))
    idx = np.nonzero(sel)[0]
    idx = idx[np.lexsort((ids[idx], typ[idx], rx[idx], step[idx]))]
    step, rx, typ, ids = step[idx], rx[idx], typ[idx], ids[idx]
    g = np.stack([np.asarray(paths[c], dtype=float)[idx] for c in _Z_COLUMNS], axis=-1)  # (n, 5)
    lm = np.stack([np.asarray(paths[c], dtype=float)[idx] for c in _LM_COLUMNS], axis=-1)  # (n, 3)
    for k, c in enumerate(_Z_COLUMNS):
        bad = ~np.isfinite(g[:, k])
        if bad.any():
            i = int(np.argmax(bad))
            raise MmslamError(f"paths column '{c}' is NaN/inf at step {step[i]} (rx {rx[i]}, "
                              f"landmark '{ids[i]}'); re-trace or repair the cache")
    point = np.asarray(is_range_gated(typ), bool)  # point scatterers: range-gated, need their position
    for k, c in enumerate(_LM_COLUMNS):
        bad = point & ~np.isfinite(lm[:, k])
        if bad.any():
            i = int(np.argmax(bad))
            raise MmslamError(f"paths column '{c}' is NaN/inf at step {step[i]} (rx {rx[i]}, "
                              f"landmark '{ids[i]}'); an SP/VS row needs its landmark position")

    # ---- per-row detection probability and noise std: constant, or from the link budget
    n = idx.size
    if link is None and sp.model == "link":
        link = LinkBudget.from_sensor(sp)
    if link is None:
        pd_row = np.full(n, sp.p_detect)
        std_row = np.broadcast_to(np.sqrt(np.diag(noise_covariance(sp))), (n, MEAS_DIM))
        snr_row = np.full(n, np.nan)
        R_out = noise_covariance(sp)
        var_clutter = np.diag(R_out)
    else:
        if "power_db" not in paths:
            raise MmslamError("paths table has no column 'power_db'; the power-aware sensor model needs it")
        snr_row = link.snr_db(np.asarray(paths["power_db"], dtype=float)[idx])
        bad = ~np.isfinite(snr_row)
        if bad.any():
            i = int(np.argmax(bad))
            raise MmslamError(f"paths column 'power_db' is {paths['power_db'][idx[i]]} at step {step[i]} (rx {rx[i]}, "
                              f"landmark '{ids[i]}'); the power-aware sensor model needs every path's power")
        pd_row = link.detect_prob(snr_row)
        std_row = link.stds(snr_row)
        var_clutter = link.stds(link.threshold_snr_db()) ** 2
        R_out = np.diag(var_clutter)

    # ---- detection (FOV + p_D) and noise
    u_det = rng.random(n)
    noise = rng.standard_normal((n, MEAS_DIM)) * std_row
    upos = true[step, rx, 0:3]
    in_fov = ~point | (np.linalg.norm(np.where(point[:, None], lm, 0.0) - upos, axis=-1) <= sp.fov_range)
    det = in_fov & (u_det < pd_row)
    z = g.copy()
    z[:, 0] += true[step, rx, 6]
    z[:, 3] = z[:, 3] - true[step, rx, 3]
    z += noise
    z[:, 1] = wrap_angle(z[:, 1])
    z[:, 3] = wrap_angle(z[:, 3])

    # ---- clutter, uniform over [0, toa_max] x (-pi, pi] x [-pi/2, pi/2] x (-pi, pi] x [-pi/2, pi/2]
    counts = rng.poisson(sp.clutter_mean, size=(steps, n_veh)) if sp.clutter_mean > 0 else np.zeros((steps, n_veh), int)
    n_c = int(counts.sum())
    uc = rng.random((n_c, MEAS_DIM))
    zc = np.empty((n_c, MEAS_DIM))
    zc[:, 0] = uc[:, 0] * sp.clutter_toa_max
    zc[:, 1] = wrap_angle(-np.pi + 2.0 * np.pi * uc[:, 1])
    zc[:, 2] = -np.pi / 2 + np.pi * uc[:, 2]
    zc[:, 3] = wrap_angle(-np.pi + 2.0 * np.pi * uc[:, 3])
    zc[:, 4] = -np.pi / 2 + np.pi * uc[:, 4]
    c_set = np.repeat(np.arange(steps * n_veh), counts.reshape(-1))

    # ---- assemble padded, shuffled sets
    d_set = (step * n_veh + rx)[det]
    all_set = np.concatenate([d_set, c_set])
    all_z = np.concatenate([z[det], zc])
    all_type = np.concatenate([typ[det], np.full(n_c, -1)]).astype(np.int8)
    all_id = np.concatenate([ids[det].astype(object), np.full(n_c, "", dtype=object)])
    all_pos = np.concatenate([np.where(typ[det, None] == OTHER, np.nan, lm[det]), np.full((n_c, 3), np.nan)])
    all_var = np.concatenate([std_row[det] ** 2, np.broadcast_to(var_clutter, (n_c, MEAS_DIM))])
    all_snr = np.concatenate([snr_row[det], np.full(n_c, np.nan)])
    keys = rng.random(all_set.size)
    order = np.lexsort((keys, all_set))
    s_sorted = all_set[order]
    J, slot, ks, vs = set_slots(s_sorted, steps, n_veh)

    Z = np.zeros((steps, n_veh, J, MEAS_DIM))
    mask = np.zeros((steps, n_veh, J), bool)
    otype = np.full((steps, n_veh, J), -1, dtype=np.int8)
    oid = np.full((steps, n_veh, J), "", dtype=object)
    opos = np.full((steps, n_veh, J, 3), np.nan)
    Z[ks, vs, slot] = all_z[order]
    mask[ks, vs, slot] = True
    otype[ks, vs, slot] = all_type[order]
    oid[ks, vs, slot] = all_id[order]
    opos[ks, vs, slot] = all_pos[order]
    rvar = np.zeros((steps, n_veh, J, MEAS_DIM))
    rvar[ks, vs, slot] = all_var[order]
    snr = np.full((steps, n_veh, J), np.nan)
    snr[ks, vs, slot] = all_snr[order]
    return Measurements(Z, mask, otype, oid, opos, true, clutter_intensity(sp), R_out, rvar, snr)
