"""Ground-truth vehicle trajectories (docs/design.md section 3).

``ct`` vehicles follow the polar coordinated turn exactly (noise-free by default).
``waypoints`` vehicles drive their route (a polyline) at their plan speed, steered by pure pursuit
under the same CT model (:func:`_waypoint_trajectory`): the state of step k+1 is the CT transition of
step k with that step's speed and turn rate, so the filter's known inputs describe the true motion
exactly, heading included, and a route of many short segments (street centrelines) is driven as a
smooth curve that rounds its corners. Waypoints ``[x, y, z]`` (street routes,
:mod:`mmslam.scenes.streets`) give the antenna height along the route: z follows the route's height
profile at the car's progress (the terrain).
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


LOOKAHEAD_STEPS = 2.0
"""Pure-pursuit lookahead of a ``waypoints`` vehicle, in steps of travel (``speed x dt`` each)."""
MIN_LOOKAHEAD = 4.0
"""m: the smallest lookahead (a slow car still rounds a polyline corner instead of pivoting on it)."""
MIN_TURN_RADIUS = 5.0
"""m: the tightest circle a ``waypoints`` car drives (a passenger car's turning circle is 10-12 m across): its
turn rate is at most ``speed / MIN_TURN_RADIUS``, and a car whose route point ahead lies behind it (a U-turn)
turns at that rate towards it."""


def _route(wps: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Plan segments ``(n - 1, 2)``, their lengths ``(n - 1,)`` and the cumulative plan length at each
    waypoint ``(n,)`` (m) of a route ``wps (n, 2 or 3)``."""
    seg = np.diff(wps[:, :2], axis=0)
    seg_len = np.linalg.norm(seg, axis=1)
    return seg, seg_len, np.concatenate([[0.0], np.cumsum(seg_len)])


def _point_at(wps: np.ndarray, cum: np.ndarray, dist: float) -> np.ndarray:
    """The route point ``(2 or 3,)`` at plan distance ``dist`` (m) from its start (clipped to the route)."""
    return np.array([np.interp(dist, cum, wps[:, c]) for c in range(wps.shape[1])])


def _project(xy: np.ndarray, heading: float, wps: np.ndarray, seg: np.ndarray, seg_len: np.ndarray,
             cum: np.ndarray, lo: float, hi: float) -> float:
    """Plan distance along the route (m) of the point of its stretch ``[lo, hi]`` nearest to ``xy (2,)``, among
    the segments that do not point against ``heading`` (rad): the vehicle's progress, searched forward from the
    last one over a short window, so neither a route that crosses itself nor the return leg of a hairpin next
    to the car is mistaken for where it is; ``lo`` when no segment qualifies (the car is still turning)."""
    best, best_d = lo, np.inf
    fwd = np.array([np.cos(heading), np.sin(heading)])
    for i in np.nonzero((cum[1:] >= lo) & (cum[:-1] <= hi) & (seg_len > 0) & (seg @ fwd >= 0.0))[0]:
        t = float(np.clip((xy - wps[i, :2]) @ seg[i] / seg_len[i] ** 2, 0.0, 1.0))
        d = float(np.linalg.norm(wps[i, :2] + t * seg[i] - xy))
        if d < best_d:
            best, best_d = float(np.clip(cum[i] + t * seg_len[i], lo, hi)), d
    return best


def drive_route(wps: np.ndarray, speed: float, steps: int, dt: float, z0: float = 0.0, bias: float = 0.0,
                heading: float | None = None) -> np.ndarray:
    """States ``(steps, 7)`` of a car that drives the route ``wps (n, 2 or 3)`` (m) at plan speed ``speed`` (m/s),
    steered by pure pursuit under the CT model, one state per step of ``dt`` s.

    Each step ``k`` the car turns at the rate ``xi_k = 2 zeta sin(a) / L_d`` that puts the CT arc of this step on
    the circle through the car and the route point ``L = max(LOOKAHEAD_STEPS zeta dt, MIN_LOOKAHEAD)`` ahead of its
    progress (``a``: that point's bearing from the heading, ``L_d`` its distance), at most ``zeta /
    MIN_TURN_RADIUS`` (and that rate, towards the point, when the point is behind the car); the state of step
    ``k + 1`` is the CT transition (:func:`~mmslam.model.vehicle_ct`) of step ``k`` with ``(zeta, xi_k)``, so the
    stored speed and turn rate describe the true motion exactly, heading included. A polyline route (street
    centrelines, many short segments) is driven as a smooth curve that rounds each corner instead of turning on the
    spot; on a straight leg the car stays on it. The start is the first waypoint, heading towards the route point
    ``L`` ahead (``heading``, when given, instead). The antenna height is ``z0`` for ``[x, y]`` waypoints, else the
    route's height profile at the car's progress (the terrain); ``bias`` fills the clock-bias column. The car stops
    (speed and turn rate 0) once its progress reaches the last waypoint, its last step shortened to the route
    length left (it ends within about a metre of the last waypoint). A change of this rule changes
    :data:`~mmslam.scenes.scenario.WAYPOINT_MOTION` (caches traced with the old one are not resumed).
    """
    wps = np.asarray(wps, dtype=float)
    seg, seg_len, cum = _route(wps)
    total = float(cum[-1])
    speed = float(speed)
    look = max(LOOKAHEAD_STEPS * speed * dt, MIN_LOOKAHEAD)
    if heading is None:
        d0 = _point_at(wps, cum, min(look, total))[:2] - wps[0, :2]
        heading = float(np.arctan2(d0[1], d0[0])) if np.hypot(*d0) > 0 else 0.0
    s = np.zeros((steps, 7))
    cur = np.array([wps[0, 0], wps[0, 1], wps[0, 2] if wps.shape[1] == 3 else z0, heading, 0.0, 0.0, bias])
    prog = 0.0
    for k in range(steps):
        left = total - prog
        zeta, xi = 0.0, 0.0
        if left > 1e-9 and speed > 0.0:
            zeta = min(speed, left / dt)  # the last step: the route length left
            d = _point_at(wps, cum, min(prog + look, total))[:2] - cur[:2]
            ld = float(np.hypot(*d))
            if ld > 0:
                a = float(wrap_angle(np.arctan2(d[1], d[0]) - cur[3]))
                xi_max = zeta / MIN_TURN_RADIUS
                xi = (float(np.clip(2.0 * zeta * np.sin(a) / ld, -xi_max, xi_max)) if np.cos(a) >= 0.0
                      else float(np.copysign(xi_max, a)))  # behind the car: turn round at the tightest circle
        cur[4], cur[5] = zeta, xi
        s[k] = cur
        if k + 1 < steps:
            cur = vehicle_ct(cur, dt)
            cur[3] = wrap_angle(cur[3])
            step = zeta * dt
            if zeta >= speed:
                prog = _project(cur[:2], cur[3], wps, seg, seg_len, cum, prog, min(prog + 1.5 * step + 0.5, total))
            elif zeta > 0.0:  # the shortened last step
                prog = total
            if wps.shape[1] == 3:
                cur[2] = float(np.interp(prog, cum, wps[:, 2]))
    return s


def _waypoint_trajectory(v: Vehicle, steps: int, dt: float) -> np.ndarray:
    """:func:`drive_route` of vehicle ``v``'s waypoints at its plan speed ``initial_state[4]`` (its antenna
    height ``initial_state[2]`` for ``[x, y]`` waypoints, its initial clock bias)."""
    return drive_route(np.asarray(v.waypoints, float), float(v.initial_state[4]), steps, dt,
                       z0=float(v.initial_state[2]), bias=float(v.initial_state[6]))


def route_height_step(v: Vehicle, dt: float) -> float:
    """The largest height change (m) in one step along vehicle ``v``'s route: the road's slope.

    The larger of ``max_s |z(s + zeta dt) - z(s)|`` over the plan distance ``s`` along the route (``z(s)`` its
    piecewise linear height profile, the plan speed ``zeta`` (m/s, ``initial_state[4]``) and step ``dt`` (s); the
    whole route's height change if it is shorter than one step) and the largest change in one step of the car
    driving it (:func:`drive_route`, to its end): on a jagged centreline the car's progress runs up to a fifth
    ahead of ``zeta dt`` per step (it drives the shorter, smooth curve). This is the systematic height drift per
    step that a motion model with a constant height must absorb as noise (a random walk smaller than the drift
    lags behind until the measurements stop pulling it back). The scene's geometry (the route on the terrain and
    how it is driven), known before any run: 0 for a ``ct`` vehicle (a planar coordinated turn), for ``[x, y]``
    waypoints and on a flat route.
    """
    wps = np.asarray(v.waypoints, dtype=float)
    if v.motion != "waypoints" or wps.ndim != 2 or wps.shape[1] != 3 or len(wps) < 2:
        return 0.0
    s = _route(wps)[2]
    z = wps[:, 2]
    step = float(v.initial_state[4]) * float(dt)
    if step >= s[-1]:
        along = float(abs(z[-1] - z[0]))
    else:  # |z(s + L) - z(s)| is piecewise linear in s: its maximum lies where s or s + L is a waypoint
        at = np.clip(np.concatenate([s, s - step]), 0.0, s[-1] - step)
        along = float(np.max(np.abs(np.interp(at + step, s, z) - np.interp(at, s, z))))
    driven = drive_route(wps, float(v.initial_state[4]), int(np.ceil(s[-1] / max(step, 1e-9))) + 3, dt)[:, 2]
    return max(along, float(np.max(np.abs(np.diff(driven)))))


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
