"""How a ``waypoints`` car drives its route: pure pursuit under the polar CT model (:func:`drive_route`).

Below the street planner (:mod:`mmslam.scenes.streets` checks its random routes' gaps on the driven positions) and
the trajectories (:mod:`mmslam.scenes.trajectory`); given a polyline and a speed, nothing looked up.
"""
from __future__ import annotations

import numpy as np

from mmslam.model import vehicle_ct, wrap_angle


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
