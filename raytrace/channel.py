"""Channel impulse / frequency responses from the ``rays`` table (pure NumPy; no Sionna needed).

The same definitions as Sionna RT's ``Paths.cir`` / ``Paths.taps`` / ``Paths.cfr`` (and checked
against them in the tests), for one transmitter (the BS) and single isotropic antennas:

- delays, per link (step, receiver), optionally normalised so that the first ray arrives at 0:
  ``tau_i' = tau_i - min_i tau_i``;
- baseband coefficient at time ``t`` (``t = n / sampling_frequency``, ``n = 0 .. num_time_steps-1``):
  ``a_i^b(t) = a_i exp(-j 2 pi f_c tau_i') exp(j 2 pi f_D,i t)`` (``a_i`` the ``rays`` gain
  ``a_re + j a_im``, ``f_c`` the carrier, ``f_D,i`` the ray's ``doppler_hz``);
- CFR at baseband frequency ``f``: ``H(f, t) = sum_i a_i^b(t) exp(-j 2 pi f tau_i')``, at the
  subcarriers ``(k - N/2) * bandwidth / N`` (``k = 0 .. N-1``, N even; odd N symmetric);
- CIR taps (sinc pulse shaping at ``bandwidth`` W): ``h_l(t) = sum_i a_i^b(t) sinc(l - W tau_i')``
  for ``l = l_min .. l_max`` (``sinc(x) = sin(pi x) / (pi x)``).

Note that Sionna's baseband phase uses the normalised delay; so does this module.

With arrays (``tx_array`` / ``rx_array`` elements per axis, :mod:`mmslam.arrays`: horizontal
half-wavelength URAs, the BS's facing down, each vehicle's facing up with its rows along the
heading) every ray is weighted by its array responses, Sionna's synthetic-array model:
``H_{m,n}(f, t) = sum_i a_i^b(t) a_rx,m(k_rx,i) a_tx,n(k_tx,i) exp(-j 2 pi f tau_i')`` with ``k_tx``
the departure direction (``aod_az, aod_el``) and ``k_rx`` the arrival direction (``aoa_az,
aoa_el``, pointing back along the incoming ray), shape ``(steps, rx, rx_ant, tx_ant, time, K)``
(Sionna's ``Paths.cfr`` order: receive antennas before transmit antennas, time before frequency).
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mmslam import arrays
from mmslam.errors import ConfigError

KINDS = ("cfr", "cir")
NPZ_KIND = "channel"
"""Tag of an ``mmslam export`` file (:data:`mmslam.outputs.NPZ_TAG`): such a file is replaced by a later export."""


def subcarrier_frequencies(n_subcarriers: int, spacing_hz: float) -> np.ndarray:
    """Baseband subcarrier frequencies (Hz), ``(n,)``: ``[-n/2 .. n/2 - 1] * spacing`` (n even),
    ``[-(n-1)/2 .. (n-1)/2] * spacing`` (n odd); as Sionna's ``subcarrier_frequencies``."""
    n = int(n_subcarriers)
    start = -n // 2 if n % 2 == 0 else -(n - 1) // 2
    return (np.arange(start, start + n) * float(spacing_hz)).astype(float)


def _links(rays: dict[str, np.ndarray], steps: np.ndarray, n_rx: int) -> np.ndarray:
    """Link index ``step_pos * n_rx + rx`` of every ray (``-1`` for rays of other steps)."""
    pos = np.full(int(max(steps.max(initial=0), rays["step"].max(initial=0))) + 1, -1, np.int64)
    pos[steps] = np.arange(steps.size)
    sp = pos[rays["step"].astype(np.int64)]
    return np.where(sp >= 0, sp * n_rx + rays["rx"].astype(np.int64), -1)


def baseband(rays: dict[str, np.ndarray], link: np.ndarray, n_links: int, carrier_hz: float,
             times_s: np.ndarray, normalize_delays: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Baseband coefficients ``(n, T)`` and (normalised) delays ``(n,)`` of the rays with ``link >= 0``.

    ``link``: per-ray link index in ``[0, n_links)`` or -1 (ignored; its rows come back zero).
    """
    tau = np.asarray(rays["delay_s"], float).copy()
    ok = link >= 0
    if normalize_delays and ok.any():
        tmin = np.full(n_links, np.inf)
        np.minimum.at(tmin, link[ok], tau[ok])
        tau[ok] -= tmin[link[ok]]
    a = np.asarray(rays["a_re"], float) + 1j * np.asarray(rays["a_im"], float)
    ab = a * np.exp(-2j * np.pi * carrier_hz * tau)
    ab = ab[:, None] * np.exp(2j * np.pi * np.asarray(rays["doppler_hz"], float)[:, None] * times_s[None, :])
    ab[~ok] = 0.0
    return ab, tau


@dataclass
class ChannelResponse:
    """A channel response per (step, receiver).

    Attributes:
        kind: ``"cfr"`` or ``"cir"``.
        h: ``(n_steps, n_rx, n_time, K)`` complex128: CFR at ``axis`` (Hz) or CIR taps at ``axis``
            (tap index l; delay ``l / bandwidth`` s).
        axis: ``(K,)`` baseband frequencies (Hz) or tap indices.
        times_s: ``(n_time,)`` sample times within each step (s).
        steps: ``(n_steps,)`` step indices. rx_names: receiver names.
        meta: settings (carrier, bandwidth, subcarriers, normalize_delays, source cache, scenario).
    """

    kind: str
    h: np.ndarray
    axis: np.ndarray
    times_s: np.ndarray
    steps: np.ndarray
    rx_names: list[str]
    meta: dict = field(default_factory=dict)

    def to_npz_bytes(self) -> bytes:
        """``.npz`` bytes: ``h`` (complex64), ``axis``, ``times_s``, ``steps``, ``rx_names``, ``meta`` (JSON),
        and the tag ``mmslam_output`` = :data:`NPZ_KIND` (:func:`mmslam.outputs.npz_bytes`)."""
        from mmslam.outputs import npz_bytes

        return npz_bytes(NPZ_KIND, compressed=True, h=self.h.astype(np.complex64), axis=self.axis,
                         times_s=self.times_s, steps=self.steps, rx_names=np.array(self.rx_names),
                         meta=np.array(json.dumps(self.meta, sort_keys=True)))


def channel_response(rays: dict[str, np.ndarray], *, kind: str, carrier_hz: float, bandwidth_hz: float,
                     n_subcarriers: int, n_rx: int, steps: np.ndarray | None = None, l_min: int = 0,
                     l_max: int | None = None, num_time_steps: int = 1, sampling_frequency_hz: float | None = None,
                     normalize_delays: bool = True, tx_array: int | None = None, rx_array: int | None = None,
                     rx_heading: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """CFR or CIR taps of every (step, rx) link from a ``rays`` table (see the module docstring).

    Args:
        rays: ``rays`` columns (at least step, rx, a_re, a_im, delay_s, doppler_hz).
        kind: ``"cfr"`` (at ``n_subcarriers`` subcarriers spaced ``bandwidth / n_subcarriers``) or
            ``"cir"`` (taps ``l_min .. l_max``, default ``l_max = n_subcarriers - 1``).
        carrier_hz: carrier frequency (Hz). bandwidth_hz: bandwidth W (Hz).
        n_rx: number of receivers. steps: steps to compute (default: all steps in ``rays``).
        num_time_steps, sampling_frequency_hz: Doppler evolution at ``t = n / fs`` (default fs = W).
        normalize_delays: first ray of each link at delay 0 (Sionna's default).
        tx_array, rx_array: BS / vehicle URA elements per axis (both or neither; None: one
            isotropic antenna each). rx_heading: ``(n_steps, n_rx)`` vehicle headings (rad) of
            the computed steps (needed with arrays).

    Returns:
        ``(h, axis (K,), times_s (T,), steps (n_steps,))`` with ``h`` of shape ``(n_steps, n_rx,
        num_time_steps, K)`` without arrays, ``(n_steps, n_rx, rx_array^2, tx_array^2,
        num_time_steps, K)`` with them.
    """
    if kind not in KINDS:
        raise ConfigError(f"kind '{kind}': expected one of {', '.join(KINDS)}")
    if not (np.isfinite(bandwidth_hz) and bandwidth_hz > 0):
        raise ConfigError(f"--bandwidth {bandwidth_hz}: expected a positive bandwidth in Hz (e.g. 400e6)")
    if int(n_subcarriers) < 1:
        raise ConfigError(f"--subcarriers {n_subcarriers}: expected a positive number")
    if int(num_time_steps) < 1:
        raise ConfigError(f"--time-steps {num_time_steps}: expected a positive number")
    if (tx_array is None) != (rx_array is None):
        raise ConfigError("channel_response: give both tx_array and rx_array or neither")
    if tx_array is not None and (int(tx_array) < 1 or int(rx_array) < 1):
        raise ConfigError(f"--tx-array {tx_array} / --rx-array {rx_array}: expected positive element counts per axis")
    steps = np.unique(np.asarray(rays["step"], np.int64)) if steps is None else np.asarray(steps, np.int64)
    fs = float(bandwidth_hz if sampling_frequency_hz is None else sampling_frequency_hz)
    times = np.arange(int(num_time_steps)) / fs
    n_links = steps.size * n_rx
    link = _links(rays, steps, n_rx) if steps.size else np.full(len(rays["step"]), -1)
    ab, tau = baseband(rays, link, n_links, carrier_hz, times, normalize_delays)
    if kind == "cfr":
        axis = subcarrier_frequencies(n_subcarriers, bandwidth_hz / n_subcarriers)
    else:
        l_max_given = l_max is not None
        l_max = int(n_subcarriers) - 1 if l_max is None else int(l_max)
        if l_max < l_min:
            src = "l_max" if l_max_given else "n_subcarriers - 1"
            raise ConfigError(f"l_min {l_min}: expected at most {src} = {l_max} (the taps are l_min .. {src})")
        axis = np.arange(int(l_min), l_max + 1, dtype=float)
    if tx_array is not None:
        heading = np.asarray(rx_heading, float) if rx_heading is not None else None
        if heading is None or heading.shape != (steps.size, n_rx):
            raise ConfigError(f"channel_response: rx_heading of shape ({steps.size}, {n_rx}) is needed with arrays")
        kern_fn = ((lambda t: np.exp(-2j * np.pi * t[:, None] * axis[None, :])) if kind == "cfr" else
                   (lambda t: np.sinc(axis[None, :] - bandwidth_hz * t[:, None]).astype(complex)))
        h = array_channel(rays, link, ab, tau, int(tx_array), int(rx_array), heading.reshape(-1), kern_fn)
        return h.reshape(steps.size, n_rx, *h.shape[1:]), axis, times, steps
    h = np.zeros((n_links, times.size, axis.size), complex)
    ok = np.flatnonzero(link >= 0)
    for s in range(0, ok.size, 4096):  # bounded memory: (block, K) kernels
        i = ok[s:s + 4096]
        if kind == "cfr":
            kern = np.exp(-2j * np.pi * tau[i, None] * axis[None, :])
        else:
            kern = np.sinc(axis[None, :] - bandwidth_hz * tau[i, None]).astype(complex)
        contrib = ab[i, :, None] * kern[:, None, :]  # (b, T, K)
        np.add.at(h, link[i], contrib)
    return h.reshape(steps.size, n_rx, times.size, axis.size), axis, times, steps


def ray_array_responses(rays: dict[str, np.ndarray], idx: np.ndarray, tx_array: int, rx_array: int,
                        heading: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Transmit and receive array responses ``((n, tx_array^2), (n, rx_array^2))`` of rays ``idx``.

    ``heading``: ``(n,)`` or scalar, the receiving vehicle's heading (rad) per ray.
    """
    ut = arrays.direction_to_local(np.asarray(rays["aod_az"], float)[idx], np.asarray(rays["aod_el"], float)[idx],
                                   0.0, arrays.BS_PITCH)
    ur = arrays.direction_to_local(np.asarray(rays["aoa_az"], float)[idx], np.asarray(rays["aoa_el"], float)[idx],
                                   heading, arrays.VEHICLE_PITCH)
    return arrays.response(tx_array, ut), arrays.response(rx_array, ur)


def array_channel(rays: dict[str, np.ndarray], link: np.ndarray, ab: np.ndarray, tau: np.ndarray, tx_array: int,
                  rx_array: int, heading: np.ndarray, kern_fn) -> np.ndarray:
    """``(n_links, rx_array^2, tx_array^2, T, K)``: per link, ``sum_i ar_i (x) at_i (x) ab_i (x) kern(tau_i)``.

    One matrix product per link: ``(rx*tx, n_i)^T`` times ``(n_i, T*K)``. ``heading (n_links,)``.
    """
    n_links = heading.size
    nr, nt = rx_array * rx_array, tx_array * tx_array
    T = ab.shape[1]
    order = np.argsort(link, kind="stable")
    lk = link[order]
    bounds = np.searchsorted(lk, np.arange(n_links + 1))
    out = None
    for L in range(n_links):
        i = order[bounds[L]:bounds[L + 1]]
        kern = kern_fn(tau[i])
        if out is None:
            out = np.zeros((n_links, nr, nt, T, kern.shape[1]), complex)
        if i.size == 0:
            continue
        at, ar = ray_array_responses(rays, i, tx_array, rx_array, heading[L])
        x = (ar[:, :, None] * at[:, None, :]).reshape(i.size, nr * nt)
        y = (ab[i, :, None] * kern[:, None, :]).reshape(i.size, -1)
        out[L] = (x.T @ y).reshape(nr, nt, T, -1)
    if out is None:
        out = np.zeros((n_links, nr, nt, T, kern_fn(np.zeros(0)).shape[1]), complex)
    return out


def cache_channel_response(cache, *, kind: str, bandwidth_hz: float, n_subcarriers: int,
                           steps: np.ndarray | None = None, l_min: int = 0, l_max: int | None = None,
                           num_time_steps: int = 1, normalize_delays: bool = True,
                           sampling_frequency_hz: float | None = None, arrays: bool = False) -> ChannelResponse:
    """:func:`channel_response` of a loaded :class:`~mmslam.raytrace.cache.PathCache` (its ``rays``).

    ``arrays``: with the scenario's BS and vehicle arrays (``sensor.tx_array`` / ``rx_array``
    elements per axis, the vehicles' headings from the cache): ``h (steps, rx, rx_ant, tx_ant,
    time, K)``; else single isotropic antennas, ``h (steps, rx, time, K)``.
    """
    rays = cache.read_rays()
    if steps is None:
        steps = np.arange(cache.steps)
    steps = np.asarray(steps, np.int64)
    bad = steps[(steps < 0) | (steps >= cache.steps)]
    if bad.size:
        raise ConfigError(f"--steps: step {int(bad[0])} is outside the cache's 0..{cache.steps - 1}")
    fc = float(cache.scenario.frequency_hz)
    sp = cache.scenario.sensor
    arr = dict(tx_array=int(sp.tx_array), rx_array=int(sp.rx_array), rx_heading=cache.states[steps, :, 3]) if arrays else {}
    h, axis, times, steps = channel_response(rays, kind=kind, carrier_hz=fc, bandwidth_hz=bandwidth_hz,
                                             n_subcarriers=n_subcarriers, n_rx=len(cache.vehicle_names),
                                             steps=steps, l_min=l_min, l_max=l_max,
                                             num_time_steps=num_time_steps, normalize_delays=normalize_delays,
                                             sampling_frequency_hz=sampling_frequency_hz, **arr)
    meta = {"kind": kind, "carrier_hz": fc, "bandwidth_hz": float(bandwidth_hz), "n_subcarriers": int(n_subcarriers),
            "normalize_delays": bool(normalize_delays), "num_time_steps": int(num_time_steps),
            "sampling_frequency_hz": float(bandwidth_hz if sampling_frequency_hz is None else sampling_frequency_hz),
            "axis": "baseband frequency (Hz)" if kind == "cfr" else "tap index l (delay l / bandwidth s)",
            "h": "(steps, rx, rx_ant, tx_ant, time, axis) complex" if arrays else "(steps, rx, time, axis) complex",
            **({"tx_array": int(sp.tx_array), "rx_array": int(sp.rx_array),
                "arrays": "mmslam.arrays: horizontal half-wavelength URAs, Sionna PlanarArray element order; "
                          "BS normal down (yaw 0), vehicle normal up (yaw = heading)"} if arrays else {}),
            "tx_position_m": [float(x) for x in cache.scenario.bs],
            "cache": str(Path(cache.path).resolve()),
            "scenario": cache.manifest["scenario"], "source": cache.manifest["source"],
            "config_hash": cache.manifest["config_hash"]}
    return ChannelResponse(kind, h, axis, times, steps, list(cache.vehicle_names), meta)
