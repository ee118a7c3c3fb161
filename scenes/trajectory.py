"""Ground-truth vehicle trajectories (docs/design.md section 3).

``ct`` vehicles follow the polar coordinated turn exactly (noise-free by default).
``waypoints`` vehicles move at constant speed along a polyline; per step the heading, speed and
turn rate are set so that the CT model maps the position at step k exactly onto the position at
step k+1 (a circular arc whose chord is the true displacement), so the filter's known inputs
(speed, turn rate) are consistent with the truth. Heading may jump by half the chord-direction
change at polyline corners; on straight legs the motion is exact. Waypoints ``[x, y, z]``
(street routes, :mod:`mmslam.scenes.streets`) give the antenna height along the route: the car
moves at its speed in plan and z is interpolated linearly (it follows the terrain).
"""
from __future__ import annotations

import numpy as np

from mmslam.scenes.scenario import Scenario, Vehicle
from mmslam.model import vehicle_ct, wrap_angle


def _ct_trajectory(v: Vehicle, steps: int, dt: float, rng: np.random.Generator | None,
                   noise_std: np.ndarray | None) -> np.ndarray:
    s = np.empty((steps, 7))
    s[0] = v.initial_state
    for k in range(1, steps):
        s[k] = vehicle_ct(s[k - 1], dt)
        if rng is not None and noise_std is not None:
            s[k] += rng.standard_normal(7) * noise_std
    return s


def _polyline_positions(wps: np.ndarray, speed: float, times: np.ndarray) -> np.ndarray:
    """Positions at ``times`` moving at plan speed ``speed`` along ``wps (k, 2 or 3)`` (z interpolated)."""
    seg = np.diff(wps, axis=0)
    seg_len = np.linalg.norm(seg[:, :2], axis=1)
    cum = np.concatenate([[0.0], np.cumsum(seg_len)])
    dist = np.minimum(speed * times, cum[-1])  # stop at the last waypoint
    i = np.clip(np.searchsorted(cum, dist, side="right") - 1, 0, len(seg) - 1)
    frac = np.where(seg_len[i] > 0, (dist - cum[i]) / np.where(seg_len[i] > 0, seg_len[i], 1.0), 0.0)
    return wps[i] + frac[:, None] * seg[i]


def _waypoint_trajectory(v: Vehicle, steps: int, dt: float) -> np.ndarray:
    wps = np.asarray(v.waypoints, dtype=float)
    t = np.arange(steps + 1) * dt
    pos = _polyline_positions(wps, v.initial_state[4], t)
    xy = pos[:, :2]
    d = np.diff(xy, axis=0)  # (steps, 2) chord of each step
    chord = np.linalg.norm(d, axis=1)
    moving = chord > 1e-9
    direc = np.where(moving, np.arctan2(d[:, 1], d[:, 0]), np.nan)
    # carry the last known direction over stopped steps (and the initial heading before motion)
    last = v.initial_state[3]
    for k in range(steps):
        if np.isnan(direc[k]):
            direc[k] = last
        last = direc[k]
    turn = np.zeros(steps)
    turn[1:] = wrap_angle(np.diff(direc)) / dt
    heading = direc - turn * dt / 2.0
    half = turn * dt / 2.0
    with np.errstate(invalid="ignore", divide="ignore"):
        speed = np.where(np.abs(half) > 1e-12, chord * half / np.sin(half) / dt, chord / dt)
    s = np.zeros((steps, 7))
    s[:, 0:2] = xy[:-1]
    s[:, 2] = pos[:-1, 2] if wps.shape[1] == 3 else v.initial_state[2]  # 3-D waypoints: z follows the terrain
    s[:, 3] = heading
    s[:, 4] = speed
    s[:, 5] = turn
    s[:, 6] = v.initial_state[6]
    return s


def route_height_step(v: Vehicle, dt: float) -> float:
    """The largest height change (m) over one step's travel along vehicle ``v``'s route: the road's slope.

    ``max_s |z(s + zeta dt) - z(s)|`` over the plan distance ``s`` along the route, ``z(s)`` its piecewise linear
    height profile, at the plan speed ``zeta`` (m/s, ``initial_state[4]``) and step ``dt`` (s); the whole route's
    height change if it is shorter than one step. This is the systematic height drift per step that a motion
    model with a constant height must absorb as noise (a random walk smaller than the drift lags behind until
    the measurements stop pulling it back). The scene's geometry (the route on the terrain), known before any
    run: 0 for a ``ct`` vehicle (a planar coordinated turn), for ``[x, y]`` waypoints and on a flat route.
    """
    wps = np.asarray(v.waypoints, dtype=float)
    if v.motion != "waypoints" or wps.ndim != 2 or wps.shape[1] != 3 or len(wps) < 2:
        return 0.0
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(wps[:, :2], axis=0), axis=1))])
    z = wps[:, 2]
    step = float(v.initial_state[4]) * float(dt)
    if step >= s[-1]:
        return float(abs(z[-1] - z[0]))
    # |z(s + L) - z(s)| is piecewise linear in s: its maximum lies where s or s + L is a waypoint
    at = np.clip(np.concatenate([s, s - step]), 0.0, s[-1] - step)
    return float(np.max(np.abs(np.interp(at + step, s, z) - np.interp(at, s, z))))


def vehicle_trajectories(scn: Scenario, steps: int | None = None,
                         rng: np.random.Generator | None = None) -> np.ndarray:
    """True vehicle states per step, shape ``(steps, n_vehicles, 7)``, global frame.

    Columns ``[x, y, z, heading, speed, turn_rate, clock_bias]`` (m, m, m, rad, m/s, rad/s, m);
    the clock bias column holds the initial bias (the sensor model draws its random walk).
    With ``rng`` given, ``ct`` vehicles get process noise ``scn.sensor.vehicle_noise_std``
    (except on the clock bias); without it the trajectory is noise-free and deterministic.
    """
    n = scn.steps if steps is None else steps
    noise = None
    if rng is not None:
        noise = np.asarray(scn.sensor.vehicle_noise_std, float).copy()
        noise[6] = 0.0
    out = np.empty((n, len(scn.vehicles), 7))
    # one child stream per vehicle: a vehicle's draws do not depend on the trajectory length
    children = rng.spawn(len(scn.vehicles)) if rng is not None else [None] * len(scn.vehicles)
    for i, v in enumerate(scn.vehicles):
        if v.motion == "ct":
            out[:, i] = _ct_trajectory(v, n, scn.dt, children[i], noise)
        else:
            out[:, i] = _waypoint_trajectory(v, n, scn.dt)
    return out


def true_trajectories(scn: Scenario, steps: int | None = None) -> np.ndarray:
    """The trajectories a trace uses as ground truth, ``(steps, n_vehicles, 7)``.

    Noise-free unless ``scn.sensor.true_process_noise`` is set; then ``ct`` vehicles get process
    noise drawn from a generator seeded by the scenario seed, so the truth is the same on every
    run and a longer trace extends a shorter one with identical first steps.
    """
    rng = np.random.default_rng([scn.seed, 0x7472616A]) if scn.sensor.true_process_noise else None
    return vehicle_trajectories(scn, steps, rng=rng)


BS_CLEARANCE_M = 0.1
"""A vehicle antenna closer than this to the BS (m) has no defined path geometry (zero TOA)."""


def check_bs_clearance(scn: Scenario, states: np.ndarray) -> None:
    """One-line :class:`~mmslam.errors.ConfigError` naming the vehicle and the BS if a vehicle antenna
    comes within :data:`BS_CLEARANCE_M` of the BS. ``states``: ``(steps, n_veh, >=3)``, m."""
    from mmslam.errors import ConfigError

    d = np.linalg.norm(np.asarray(states)[:, :, :3] - scn.bs_array, axis=2)
    if d.size and d.min() < BS_CLEARANCE_M:
        k, i = np.unravel_index(int(np.argmin(d)), d.shape)
        raise ConfigError(f"{scn.source_file}: vehicle '{scn.vehicles[i].name}' is {d[k, i]:.3g} m from the BS "
                          f"{list(scn.bs)} at step {k} (at least {BS_CLEARANCE_M} m needed); move the BS or the "
                          "vehicle's trajectory")
