"""Sensor model ``estimated`` (issue 24): measurements estimated from the received MIMO-OFDM pilots.

Per vehicle and step, from every traced ray of its link (``rays`` table, all types):

1. **pilots** (:class:`PilotModel`, :func:`received_pilots`): the full MIMO-OFDM channel is observed
   once per step. The BS sends one pilot OFDM symbol per transmit element (``tx_array^2`` symbols,
   time-orthogonal), each at the full transmit power over ``K = est_subcarriers`` subcarriers spanning
   the bandwidth ``B``; the vehicle samples all ``rx_array^2`` elements (a digital array). Per
   subcarrier the pilot power is ``P / K`` and the noise ``N0 B / K``, so every entry of the
   observed channel has the wideband SNR: ``Y = s H + W``, ``W ~ CN(0, 1)``, ``s^2 = P_tx / (N0 B F)``
   times the processing gain (``tx_power_dbm - noise_dbm + processing_gain_db``, the link budget's
   terms without the array gains: the arrays are in ``H``). Full-channel pilots rather than beam
   sweeping: the estimator then sees every path in one step at the full aperture of both arrays
   (beam sweeping with ``tx^2 rx^2`` beam pairs gives the same energy per path but needs a codebook
   and loses the paths between beams); the cost is ``tx^2`` pilot symbols per step, 64 x 0.64 us
   at 256 subcarriers, far below the 0.5 s step. ``H`` is :func:`mmslam.raytrace.channel` 's array
   channel at the absolute delays plus the clock bias, after the receiver's window start ``t0``:
   the first arrival's sample (its timing acquisition) minus ``GUARD`` samples. Noise is drawn from
   the caller's generator, one ``(rx, tx, K)`` complex normal block per (step, vehicle) in order.
2. **estimator** (:mod:`mmslam.slam.sim.channel_estimator`): NOMP with a CFAR stop at ``est_pfa`` per
   vehicle-step, at most ``est_max_paths`` estimates; each estimate ``z = [t0 + tau (m), AOD az,
   AOD el, AOA az - heading, AOA el]`` with its Fisher-information covariance; a delay earlier than the
   first arrival is unwrapped by one window (:func:`unwrap_delay`).
3. **non-maximum suppression** (:func:`suppress_non_maxima`, ``est_resolve`` cells, applied to the cached
   estimates by :func:`resolve_estimates`, so changing it does not re-estimate): of estimates of one link
   within ``est_resolve`` cells of each other in every axis, only the strongest is kept.
   The filter gets each kept estimate's Fisher-information variances, the TOA's with a floor
   ``est_toa_floor`` (:func:`measurement_variances`).
4. **evaluation labels** (:func:`associate`, never seen by the filter): each estimate is matched to
   the traced rays within one resolution cell in every axis; its label is the landmark of the
   strongest such ray, ``merged`` if rays of two or more landmarks fall in the cell, ``false`` if
   none. A landmark of the ``paths`` table with no estimate labelled with it is ``missed``.

Estimates of a whole Monte Carlo run are cached (:func:`estimated_run`) under
``CACHE/estimates/<key>/seed-<s>.npz`` (atomic writes; ``key`` a hash of the settings that change
them), so that ablations over filter options do not re-estimate.
"""
from __future__ import annotations

import hashlib
import io
import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mmslam.scenes.scenario import Scenario, SensorParams

from . import channel_estimator as ce
from ..models.dynamics import wrap_angle
from ..models.measurement import MEAS_DIM, OTHER
from .sensor import BOLTZMANN_DBM_HZ, Measurements, clock_bias_walk, clutter_intensity, set_slots

SPEED_OF_LIGHT = ce.SPEED_OF_LIGHT
GUARD = 4
"""Samples (``1 / B`` each) the receiver's window opens before the first arrival."""
ESTIMATOR_VERSION = 3
"""Part of the estimates' cache key: bump when the estimator's results change."""


@dataclass(frozen=True)
class PilotModel:
    """Geometry and SNR scale of the received pilots (module docstring, item 1)."""

    grid: ce.Grid
    carrier_hz: float
    snr_scale_db: float

    @classmethod
    def from_sensor(cls, sp: SensorParams, carrier_hz: float) -> "PilotModel":
        noise_dbm = BOLTZMANN_DBM_HZ + 10.0 * math.log10(sp.bandwidth_hz) + sp.noise_figure_db
        return cls(ce.Grid(int(sp.tx_array), int(sp.rx_array), int(sp.est_subcarriers), float(sp.bandwidth_hz)),
                   float(carrier_hz), float(sp.tx_power_dbm - noise_dbm + sp.processing_gain_db))

    def window_start_m(self, toa_m: np.ndarray) -> float:
        """Window start (m, receiver clock): the first arrival's sample minus :data:`GUARD` samples."""
        dr = SPEED_OF_LIGHT / self.grid.bandwidth_hz
        return float((math.floor(float(np.min(toa_m)) / dr) - GUARD) * dr)


def received_pilots(rays: dict[str, np.ndarray], idx: np.ndarray, heading: float, bias_m: float,
                    pm: PilotModel, rng: np.random.Generator | None) -> tuple[np.ndarray, float]:
    """The observed channel ``Y (rx^2, tx^2, K)`` (unit noise) of rays ``idx`` of one link, and ``t0`` (m).

    ``heading`` (rad), ``bias_m`` the true clock bias (m). ``rng`` None: noise-free.
    """
    from mmslam.raytrace.channel import ray_array_responses

    g = pm.grid
    toa = np.asarray(rays["delay_s"], float)[idx] * SPEED_OF_LIGHT + bias_m
    t0 = pm.window_start_m(toa) if idx.size else 0.0
    a = (np.asarray(rays["a_re"], float)[idx] + 1j * np.asarray(rays["a_im"], float)[idx])
    a = a * np.exp(-2j * np.pi * pm.carrier_hz * np.asarray(rays["delay_s"], float)[idx]) * 10 ** (pm.snr_scale_db / 20)
    at, ar = ray_array_responses(rays, idx, g.tx_array, g.rx_array, heading)
    f = (np.arange(g.n_subcarriers) - g.n_subcarriers // 2) * g.spacing_hz
    kern = np.exp(-2j * np.pi * np.outer((toa - t0) / SPEED_OF_LIGHT, f))
    Y = ((ar[:, :, None] * at[:, None, :]).reshape(idx.size, g.rx_array ** 2 * g.tx_array ** 2).T
         @ (a[:, None] * kern)).reshape(
        g.rx_array ** 2, g.tx_array ** 2, g.n_subcarriers)
    if rng is not None:
        Y = Y + (rng.standard_normal(Y.shape) + 1j * rng.standard_normal(Y.shape)) / math.sqrt(2.0)
    return Y, t0


def unwrap_delay(z: np.ndarray, t0_m: float, grid: ce.Grid) -> np.ndarray:
    """Estimates ``z (L, 5)`` with the delay aliasing of the DFT window undone (a copy).

    The delay axis is periodic with the window ``W = K c / B`` (192 m at 256 subcarriers and 400 MHz): a
    path longer than ``t0 + W`` appears ``W`` too early. The receiver opened its window :data:`GUARD`
    samples before its first arrival, so an estimate more than one sample earlier than that
    (``z_toa - t0 < (GUARD - 1) c / B``) cannot be a path of this link as it is: it is one from beyond the
    window's end, and gets ``W`` added. This undoes the aliasing of excess delays in
    ``[W - tau_1, W - tau_1 + (GUARD - 1) c / B)`` (``tau_1`` the first arrival's delay into the window,
    ``GUARD`` to ``GUARD + 1`` samples: about the last three samples before ``W``); a longer path
    aliases to after the first arrival and is not told apart (a larger ``est_subcarriers`` is then needed).
    On the ``paper`` Sionna trace the far wall's VA (189-193 m of excess delay) was aliased in 5.7 % of the
    VA estimates, 0.3 % with this (docs/estimator.md, 3d).
    """
    z = np.array(z, float, copy=True)
    dr = SPEED_OF_LIGHT / grid.bandwidth_hz
    early = z[:, 0] - t0_m < (GUARD - 1) * dr
    z[early, 0] += grid.n_subcarriers * dr
    return z


def estimate_link(Y: np.ndarray, t0_m: float, pm: PilotModel, pfa: float, max_paths: int
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Estimates of one link: ``z (L, 5)``, covariances ``(L, 5, 5)``, integrated SNR ``|g|^2 N`` (dB)
    ``(L,)`` and the frequencies ``w (L, 5)``."""
    w, g = ce.nomp(Y, pm.grid, pfa, max_paths)
    z = unwrap_delay(ce.measurement_of_w(w, t0_m, pm.grid), t0_m, pm.grid)
    cov = ce.measurement_covariance(z, g, t0_m, pm.grid) if len(g) else np.zeros((0, 5, 5))
    snr = 10.0 * np.log10(np.abs(g) ** 2 * pm.grid.size) if len(g) else np.zeros(0)
    return z, cov, snr, w


def estimator_kernels_cached() -> bool:
    """Whether every compiled kernel of the estimator (:mod:`mmslam.slam.sim.nomp_kernels`,
    :mod:`mmslam.slam.sim.dft_kernels`) is loaded or in numba's on-disk cache (its private cache index, as
    :func:`mmslam.slam.filter.precompile.is_cached`; any error: False)."""
    import numba.core.registry as reg

    from . import dft_kernels, nomp_kernels

    kernels = [obj for mod in (nomp_kernels, dft_kernels) for obj in vars(mod).values()
               if isinstance(obj, reg.CPUDispatcher) and obj.py_func.__module__ == mod.__name__]
    for obj in kernels:
        if obj.overloads:
            continue
        try:
            if not obj._cache._cache_file._load_index():
                return False
        except Exception:  # noqa: BLE001 (a numba without these internals)
            return False
    return True


def warm_up_estimator(sp: SensorParams, carrier_hz: float) -> None:
    """Compile (first time) or load (later) the estimator's kernels before a run's clock starts: estimate
    one noise-free synthetic link of two paths on the grid of ``sp`` (a detection, the Newton refinement
    and a cyclic-move test, so every kernel the estimator calls). Changes nothing else; no random draw."""
    pm = PilotModel.from_sensor(sp, carrier_hz)
    amp = 0.1 * 10 ** (-pm.snr_scale_db / 20.0)  # -20 dB per sample, ~+34 dB integrated: both detected
    rays = {"delay_s": np.array([2.0e-7, 2.4e-7]), "a_re": np.array([amp, 0.5 * amp]), "a_im": np.array([0.0, 0.3 * amp]),
            "aod_az": np.array([0.3, -0.5]), "aod_el": np.array([-0.2, -0.1]), "aoa_az": np.array([2.0, 1.0]),
            "aoa_el": np.array([0.1, 0.2])}
    Y, t0 = received_pilots(rays, np.arange(2), 0.0, 0.0, pm, None)
    estimate_link(Y, t0, pm, float(sp.est_pfa), int(sp.est_max_paths))


def associate(w_hat: np.ndarray, w_true: np.ndarray, power: np.ndarray, lm_key: np.ndarray, grid: ce.Grid
              ) -> tuple[np.ndarray, np.ndarray]:
    """Evaluation labels of one link's estimates.

    Args:
        w_hat: ``(L, 5)`` estimated frequencies; w_true: ``(n, 5)`` those of the traced rays;
        power: ``(n,)`` ray powers (any monotone scale); lm_key: ``(n,)`` int landmark key per ray.
        grid: the estimator's grid (cell sizes ``2 pi / L_d``).

    Returns:
        ``(label (L,), n_lm (L,))``: the strongest ray's key among the rays within one cell in every
        axis of the estimate (-1: none, a false alarm), and how many distinct landmarks are there
        (>= 2: merged).
    """
    L = w_hat.shape[0]
    label = np.full(L, -1, np.int64)
    n_lm = np.zeros(L, np.int64)
    if L == 0 or w_true.shape[0] == 0:
        return label, n_lm
    cell = 2.0 * np.pi / np.asarray(grid.shape, float)
    d = np.abs(wrap_angle(w_hat[:, None, :] - w_true[None, :, :])) / cell  # (L, n, 5) in cells
    near = np.all(d <= 1.0, axis=-1)
    for l in range(L):
        i = np.flatnonzero(near[l])
        if i.size:
            label[l] = lm_key[i[np.argmax(power[i])]]
            n_lm[l] = np.unique(lm_key[i]).size
    return label, n_lm


def settings_key(scn: Scenario) -> str:
    """Hash of everything that changes the estimates of a cache (besides the Monte Carlo seed)."""
    sp = scn.sensor
    keys = ("tx_array", "rx_array", "est_subcarriers", "est_pfa", "est_max_paths", "bandwidth_hz", "tx_power_dbm",
            "noise_figure_db", "processing_gain_db")
    d = {k: getattr(sp, k) for k in keys}
    d["clock_bias_std"] = sp.vehicle_noise_std[6]
    d.update(version=ESTIMATOR_VERSION, guard=GUARD, carrier_hz=scn.frequency_hz)
    return hashlib.sha256(json.dumps(d, sort_keys=True).encode()).hexdigest()[:16]


COUNT_COLUMNS = ("estimates", "detected", "merged", "false", "missed")
"""Per (step, vehicle) evaluation counts: estimates; estimates labelled with a landmark (one label
each); of those with two or more landmarks in their cell; estimates without any ray in their cell;
landmarks of the ``paths`` table no estimate is labelled with."""
RESOLVED_COLUMNS = COUNT_COLUMNS + ("suppressed",)
"""The counts of :func:`resolve_estimates`: :data:`COUNT_COLUMNS` of the estimates the filter gets (after
the non-maximum suppression) and the number of estimates it dropped."""


def estimate_run(scn: Scenario, states: np.ndarray, rays: dict[str, np.ndarray], paths: dict[str, np.ndarray],
                 rng: np.random.Generator) -> dict[str, np.ndarray]:
    """Estimates of one Monte Carlo run (every step and vehicle of ``states``), as flat arrays.

    Returns a dict: ``true_states (steps, n_veh, 7)`` (with the clock-bias walk, drawn first from
    ``rng``), ``set (M,)`` (``step * n_veh + vehicle``), ``z (M, 5)``, ``cov (M, 5, 5)``,
    ``snr_db (M,)``, ``origin_type (M,)`` (-1: false alarm), ``origin_id (M,)`` str, ``origin_pos
    (M, 3)``, ``merged (M,)`` bool, ``counts (steps, n_veh, 5)`` (:data:`COUNT_COLUMNS`).
    """
    sp = scn.sensor
    pm = PilotModel.from_sensor(sp, scn.frequency_hz)
    steps, n_veh = states.shape[:2]
    true = clock_bias_walk(np.asarray(states, float), sp.vehicle_noise_std[6], rng)
    r_step = np.asarray(rays["step"], np.int64)
    r_rx = np.asarray(rays["rx"], np.int64)
    r_type = np.asarray(rays["type"], np.int64)
    r_id = np.asarray(rays["landmark_id"]).astype(str)
    r_pow = np.asarray(rays["power_db"], float)
    p_step, p_rx = np.asarray(paths["step"], np.int64), np.asarray(paths["rx"], np.int64)
    p_type, p_id = np.asarray(paths["type"], np.int64), np.asarray(paths["landmark_id"]).astype(str)
    p_pos = np.stack([np.asarray(paths[c], float) for c in ("lm_x", "lm_y", "lm_z")], -1)
    out: dict[str, list] = {k: [] for k in ("set", "z", "cov", "snr_db", "origin_type", "origin_id", "origin_pos",
                                            "merged")}
    counts = np.zeros((steps, n_veh, len(COUNT_COLUMNS)), np.int64)
    order = np.lexsort((r_rx, r_step))
    bounds = np.searchsorted(r_step[order] * n_veh + r_rx[order], np.arange(steps * n_veh + 1))
    for k in range(steps):
        for v in range(n_veh):
            idx = order[bounds[k * n_veh + v]:bounds[k * n_veh + v + 1]]
            Y, t0 = received_pilots(rays, idx, float(true[k, v, 3]), float(true[k, v, 6]), pm, rng)
            z, cov, snr, w = estimate_link(Y, t0, pm, sp.est_pfa, sp.est_max_paths)
            z[:, 3] = wrap_angle(z[:, 3])
            # evaluation only: the true rays' frequencies and landmark keys
            zt = np.stack([np.asarray(rays["delay_s"], float)[idx] * SPEED_OF_LIGHT + true[k, v, 6],
                           np.asarray(rays["aod_az"], float)[idx], np.asarray(rays["aod_el"], float)[idx],
                           np.asarray(rays["aoa_az"], float)[idx] - true[k, v, 3],
                           np.asarray(rays["aoa_el"], float)[idx]], -1)
            keys = np.array([f"{t}|{i}" for t, i in zip(r_type[idx], r_id[idx])])
            uniq, key = np.unique(keys, return_inverse=True)
            label, n_lm = associate(w, ce.w_of_measurement(zt, t0, pm.grid), r_pow[idx], key, pm.grid)
            sel_p = np.flatnonzero((p_step == k) & (p_rx == v))
            lm_of_path = {f"{p_type[i]}|{p_id[i]}": i for i in sel_p}
            otype = np.full(len(label), -1, np.int64)
            oid = np.full(len(label), "", object)
            opos = np.full((len(label), 3), np.nan)
            for l, lab in enumerate(label):
                if lab >= 0:
                    t_s, i_s = uniq[lab].split("|", 1)
                    otype[l], oid[l] = int(t_s), i_s
                    if uniq[lab] in lm_of_path and int(t_s) != OTHER:
                        opos[l] = p_pos[lm_of_path[uniq[lab]]]
            found = {uniq[lab] for lab in label if lab >= 0}
            counts[k, v] = (len(label), int((label >= 0).sum()), int((n_lm >= 2).sum()), int((label < 0).sum()),
                            sum(1 for key_ in lm_of_path if key_ not in found))
            out["set"].append(np.full(len(label), k * n_veh + v, np.int64))
            for name, val in (("z", z), ("cov", cov), ("snr_db", snr), ("origin_type", otype), ("origin_id", oid),
                              ("origin_pos", opos), ("merged", n_lm >= 2)):
                out[name].append(val)
    res = {k: np.concatenate(v) if v else np.zeros(0) for k, v in out.items()}
    res["z"] = res["z"].reshape(-1, MEAS_DIM)
    res["cov"] = res["cov"].reshape(-1, MEAS_DIM, MEAS_DIM)
    res["origin_pos"] = res["origin_pos"].reshape(-1, 3)
    res["true_states"] = true
    res["counts"] = counts
    return res


def _npz_bytes(d: dict[str, np.ndarray]) -> bytes:
    buf = io.BytesIO()
    np.savez_compressed(buf, **{k: (v.astype(str) if v.dtype == object else v) for k, v in d.items()})
    return buf.getvalue()


def estimated_run(scn: Scenario, states: np.ndarray, rays: dict[str, np.ndarray], paths: dict[str, np.ndarray],
                  rng: np.random.Generator, cache_dir: str | Path | None = None, seed: int | None = None
                  ) -> dict[str, np.ndarray]:
    """:func:`estimate_run`, cached under ``cache_dir/estimates/<settings_key>/seed-<seed>-steps-<n>.npz``
    when ``cache_dir`` and ``seed`` are given (read back if present; written atomically)."""
    path = None
    if cache_dir is not None and seed is not None:
        path = (Path(cache_dir) / "estimates" / settings_key(scn) / f"seed-{int(seed)}-steps-{states.shape[0]}.npz")
        if path.is_file():
            with np.load(path, allow_pickle=False) as f:
                d = {k: f[k] for k in f.files}
            d["origin_id"] = d["origin_id"].astype(object)
            return d
    res = estimate_run(scn, states, rays, paths, rng)
    if path is not None:
        from mmslam.outputs import atomic_write_bytes

        path.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_bytes(path, _npz_bytes(res))
    return res


def suppress_non_maxima(w: np.ndarray, snr_db: np.ndarray, grid: ce.Grid, cells: float) -> np.ndarray:
    """Greedy non-maximum suppression of one link's estimates in the estimator's frequency space.

    In order of decreasing SNR, a kept estimate drops every weaker estimate within ``cells``
    resolution cells of it in all five axes at once (``|wrap(w_i,d - w_j,d)| <= cells 2 pi / L_d`` for
    every axis ``d``; a dropped estimate drops nothing). A path's main lobe is two cells wide (null to
    null, +-1 cell) in each axis, so at ``cells = 2`` a kept estimate owns the estimates inside its main
    lobe and its first sidelobes: the diffuse rays around a specular path that NOMP fits as separate atoms (docs/estimator.md, 3b).

    Args:
        w: ``(L, 5)`` estimated frequencies (rad; :func:`~.channel_estimator.w_of_measurement`, any
            delay origin: only differences enter). snr_db: ``(L,)`` integrated SNRs (dB; any
            monotone strength). grid: the estimator's grid (axis lengths ``L_d``).
        cells: suppression radius in cells (<= 0: keep every estimate).

    Returns:
        ``keep (L,)`` bool. Equal SNRs: the earlier estimate is the stronger.
    """
    w, snr_db = np.asarray(w, float).reshape(-1, MEAS_DIM), np.asarray(snr_db, float).reshape(-1)
    keep = np.ones(snr_db.shape[0], bool)
    if cells <= 0 or keep.size < 2:
        return keep
    cell = 2.0 * np.pi / np.asarray(grid.shape, float)
    near = np.all(np.abs(wrap_angle(w[:, None, :] - w[None, :, :])) <= cells * cell, axis=-1)  # (L, L)
    order = np.argsort(-snr_db, kind="stable")
    for pos, i in enumerate(order):
        if keep[i]:
            later = order[pos + 1:]
            keep[later[near[i, later]]] = False
    return keep


def resolve_estimates(scn: Scenario, est: dict[str, np.ndarray], steps: int, n_veh: int,
                      paths: dict[str, np.ndarray] | None = None) -> dict[str, np.ndarray]:
    """An :func:`estimate_run` result after :func:`suppress_non_maxima` of every link (``sensor.est_resolve``).

    Returns the same dict with the per-estimate arrays of the kept estimates and ``counts (steps, n_veh, 6)``
    (:data:`RESOLVED_COLUMNS`): the evaluation counts recomputed over the kept estimates and the number
    dropped. ``missed``: with the run's ``paths`` table, a landmark of it whose every labelled estimate was
    dropped is added to the cached count (exact, :func:`estimate_run`'s definition); without it, only BS /
    VA / SP / VS landmarks (those with a stored position) are. The input is not modified.
    """
    s = np.asarray(est["set"], np.int64)
    grid = PilotModel.from_sensor(scn.sensor, scn.frequency_hz).grid
    keep = np.ones(s.size, bool)
    z, snr = np.asarray(est["z"], float).reshape(-1, MEAS_DIM), np.asarray(est["snr_db"], float)
    for u in np.unique(s):
        i = np.flatnonzero(s == u)
        keep[i] = suppress_non_maxima(ce.w_of_measurement(z[i], 0.0, grid), snr[i], grid, scn.sensor.est_resolve)
    per_estimate = ("set", "z", "cov", "snr_db", "origin_type", "origin_id", "origin_pos", "merged")
    out = {k: (np.asarray(v)[keep] if k in per_estimate else v) for k, v in est.items()}
    old = np.asarray(est["counts"], np.int64)[:steps]
    counts = np.zeros((old.shape[0], n_veh, len(RESOLVED_COLUMNS)), np.int64)
    counts[..., 4] = old[..., 4]  # missed before the suppression
    otype, oid, merged = np.asarray(est["origin_type"]), np.asarray(est["origin_id"]).astype(str), np.asarray(est["merged"], bool)
    if paths is not None:  # landmark keys of the paths table per link, as estimate_run's missed count
        p_key = {}
        for st_, rx_, ty_, id_ in zip(np.asarray(paths["step"]), np.asarray(paths["rx"]), np.asarray(paths["type"]),
                                      np.asarray(paths["landmark_id"]).astype(str)):
            p_key.setdefault(int(st_) * n_veh + int(rx_), set()).add((int(ty_), id_))
        counted = np.array([(int(t_), i_) in p_key.get(int(u_), ()) for u_, t_, i_ in zip(s, otype, oid)], bool)
    else:
        counted = np.isfinite(np.asarray(est["origin_pos"], float).reshape(-1, 3)[:, 0])
    for u in np.unique(s):
        k, v = divmod(int(u), n_veh)
        if k >= counts.shape[0]:
            continue
        i = np.flatnonzero(s == u)
        kept = i[keep[i]]
        found_before = {(int(otype[j]), oid[j]) for j in i[counted[i]]}
        found_after = {(int(otype[j]), oid[j]) for j in kept[counted[kept]]}
        counts[k, v, :4] = (kept.size, int((otype[kept] >= 0).sum()), int(merged[kept].sum()), int((otype[kept] < 0).sum()))
        counts[k, v, 4] += len(found_before - found_after)
        counts[k, v, 5] = i.size - kept.size
    out["counts"] = counts
    return out


def threshold_covariance(scn: Scenario) -> np.ndarray:
    """``(5, 5)`` covariance of an estimate at the CFAR threshold SNR, AOD elevation -20 deg, AOA elevation
    +20 deg, azimuths 0 (the shared ``R`` of :class:`Measurements`)."""
    pm = PilotModel.from_sensor(scn.sensor, scn.frequency_hz)
    g = math.sqrt(ce.cfar_threshold(pm.grid, scn.sensor.est_pfa))
    z = np.array([[50.0, 0.0, -0.35, 0.0, 0.35]])
    cov = ce.measurement_covariance(z, np.array([g]), 0.0, pm.grid)[0]
    cov[0, 0] += scn.sensor.est_toa_floor ** 2  # as every estimate's (measurement_variances)
    return cov


def measurement_variances(scn: Scenario, cov: np.ndarray) -> np.ndarray:
    """``(M, 5)`` variances the filter gets for estimates with Fisher-information covariances ``cov (M, 5, 5)``:
    their diagonals, the TOA's (m^2) plus ``sensor.est_toa_floor^2``.

    The Fisher information bounds the error of an estimate of one isolated path. A second component closer
    than the delay resolution (``c / B``) is not resolved: a bias no SNR removes, set by the components'
    amplitude ratio ``rho`` and relative phase (to first order ``d rho / (1 + rho)`` after the first in
    phase, their amplitude-weighted centre; ``d rho / (1 - rho)`` before it in anti-phase). A roof antenna
    always has one: the roof's specular reflection, ``2 h sin(el)`` later for an antenna ``h`` above the
    roof, 1 dB weaker on the ``paper`` trace, its phase turning with the elevation; measured error of the
    line-of-sight estimates: median +2.1 cm, RMS 3.9 cm (``paper``) and +1.4 cm, 4.4 cm (``canyon``), against
    a Fisher standard deviation of 0.4 mm (docs/estimator.md, 3c).
    """
    var = np.diagonal(np.asarray(cov, float), axis1=-2, axis2=-1).copy()
    var[..., 0] += scn.sensor.est_toa_floor ** 2
    return var


def to_measurements(scn: Scenario, est: dict[str, np.ndarray], steps: int, n_veh: int) -> Measurements:
    """Padded :class:`Measurements` of an :func:`estimate_run` result (order: as estimated)."""
    s = np.asarray(est["set"], np.int64)
    J, slot, ks, vs = set_slots(s, steps, n_veh)
    Z = np.zeros((steps, n_veh, J, MEAS_DIM))
    mask = np.zeros((steps, n_veh, J), bool)
    otype = np.full((steps, n_veh, J), -1, np.int8)
    oid = np.full((steps, n_veh, J), "", dtype=object)
    opos = np.full((steps, n_veh, J, 3), np.nan)
    rvar = np.zeros((steps, n_veh, J, MEAS_DIM))
    snr = np.full((steps, n_veh, J), np.nan)
    Z[ks, vs, slot] = est["z"]
    mask[ks, vs, slot] = True
    otype[ks, vs, slot] = est["origin_type"]
    oid[ks, vs, slot] = est["origin_id"]
    opos[ks, vs, slot] = est["origin_pos"]
    rvar[ks, vs, slot] = measurement_variances(scn, est["cov"])
    snr[ks, vs, slot] = est["snr_db"]
    return Measurements(Z, mask, otype, oid, opos, np.asarray(est["true_states"], float), clutter_intensity(scn.sensor),
                        threshold_covariance(scn), rvar, snr)
