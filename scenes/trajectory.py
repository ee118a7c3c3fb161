"""Ground-truth vehicle trajectories (docs/design.md section 3).

``ct`` vehicles follow the polar coordinated turn exactly (noise-free by default).
``waypoints`` vehicles drive their route (a polyline) at their plan speed, steered by pure pursuit
under the same CT model (:func:`mmslam.scenes.driving.drive_route`): the state of step k+1 is the CT transition of
step k with that step's speed and turn rate, so the filter's known inputs describe the true motion
exactly, heading included, and a route of many short segments (street centrelines) is driven as a
smooth curve that rounds its corners. Waypoints ``[x, y, z]`` (street routes,
:mod:`mmslam.scenes.streets`) give the antenna height along the route: z follows the route's height
profile at the car's progress (the terrain).
"""
from __future__ import annotations

import numpy as np

from mmslam.scenes.scenario import Scenario, Vehicle
from mmslam.model import vehicle_ct
from mmslam.scenes.driving import _route, drive_route


def _ct_trajectory(v: Vehicle, steps: int, dt: float, rng: np.random.Generator | None,
                   noise_std: np.ndarray | None) -> np.ndarray:
    s = np.empty((steps, 7))
    s[0] = v.initial_state
    for k in range(1, steps):
        s[k] = vehicle_ct(s[k - 1], dt)
        if rng is not None and noise_std is not None:
            s[k] += rng.standard_normal(7) * noise_std
    return s


def _waypoint_trajectory(v: Vehicle, steps: int, dt: float) -> np.ndarray:
    """:func:`drive_route` of vehicle ``v``'s waypoints at its plan speed ``initial_state[4]`` (its antenna
    height ``initial_state[2]`` for ``[x, y]`` waypoints, its initial clock bias)."""
    return drive_route(np.asarray(v.waypoints, float), float(v.initial_state[4]), steps, dt,
                       z0=float(v.initial_state[2]), bias=float(v.initial_state[6]))


MAX_DRIVEN_STEPS = 20_000
"""The most steps :func:`route_height_step` drives a route for (a few seconds; a 2 km route at 0.2 m/s, dt 0.5 s)."""


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
    waypoints and on a flat route. The car is driven for at most :data:`MAX_DRIVEN_STEPS` steps (a car slower than
    the route's length in that many steps, mm/s on a street, is driven for its first part only).
    """
    wps = np.asarray(v.waypoints, dtype=float)
    if v.motion != "waypoints" or wps.ndim != 2 or wps.shape[1] != 3 or len(wps) < 2:
        return 0.0
    s = _route(wps)[2]
    z = wps[:, 2]
    step = float(v.initial_state[4]) * float(dt)
    if step <= 0.0:  # a car that does not move
        return 0.0
    if step >= s[-1]:
        along = float(abs(z[-1] - z[0]))
    else:  # |z(s + L) - z(s)| is piecewise linear in s: its maximum lies where s or s + L is a waypoint
        at = np.clip(np.concatenate([s, s - step]), 0.0, s[-1] - step)
        along = float(np.max(np.abs(np.interp(at + step, s, z) - np.interp(at, s, z))))
    n = int(min(np.ceil(s[-1] / step) + 3, MAX_DRIVEN_STEPS))
    driven = drive_route(wps, float(v.initial_state[4]), n, dt)[:, 2]
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


DETOUR_RATIO = 1.5
"""A route whose streets run more than this many times the straight line through its route points (and
:data:`DETOUR_SLACK_M` more) is reported by :func:`route_warnings`. Routes written on the streets run 1.02-1.18 times
it (the held-out scenarios of ``benchmarks/scenes``)."""
DETOUR_SLACK_M = 20.0
"""m: the detour a route may take beyond :data:`DETOUR_RATIO` before :func:`route_warnings` reports it (the snap of
its two ends to the centrelines moves each up to about 10 m)."""
STOP_SHARE = 0.1
"""A car that stands still at its route's end for at least this share of the steps (and at least 2) is reported by
:func:`route_warnings` (a car on a curved route gains up to a fifth on ``speed x dt`` per step, so one whose route is
just its drive's length ends a step or two early: two of the held-out ``sanfrancisco`` cars)."""


def route_warnings(scn: Scenario, traj: np.ndarray, route_points: dict[str, np.ndarray] | None = None,
                   source: str | None = None) -> list[str]:
    """One line per problem of each vehicle with a ``route`` in its scenario file whose drive is not what the file
    asks for (cars drawn by ``n_vehicles`` and explicit ``waypoints`` are not checked: their routes are not the
    user's points).

    - **A detour**: the streets join its route points (the file's ``route``, ``(k, 2)`` m) by a planned path
      (its waypoints) longer than :data:`DETOUR_RATIO` times the straight line through them plus
      :data:`DETOUR_SLACK_M`. A point on a street with no free space for a car (too narrow: ``mmslam scene
      streets`` draws the free space) is moved to the nearest drivable street, and the route then runs along
      streets the user did not choose (streets winding between two points far apart do it too: a line, not an
      error).
    - **A stop**: the car reaches the end of its route before the last step and stands still (speed 0) from then
      on, for at least :data:`STOP_SHARE` of the steps (the route is shorter than ``speed x dt x steps``).

    Args:
        scn: the scenario.
        traj: ``(steps, n_veh, 7)`` its true states (:func:`true_trajectories`).
        route_points: vehicle name -> its route points ``(k, 2)`` (m) (:func:`mmslam.scenes.scenario.scenario_route_points`); a vehicle not
            in it is not checked.
        source: how to name the file in the advice (default ``scn.source_file``).
    """
    out = []
    where = source or scn.source_file
    for i, v in enumerate(scn.vehicles):
        if v.motion != "waypoints":
            continue
        wps = np.asarray(v.waypoints, float)
        pts = None if route_points is None else route_points.get(v.name)
        if pts is None or len(pts) < 2 or len(wps) < 2:
            continue
        plan = float(_route(wps)[2][-1])
        straight = float(np.hypot(*np.diff(np.asarray(pts, float)[:, :2], axis=0).T).sum())
        if plan > DETOUR_RATIO * straight + DETOUR_SLACK_M:
            out.append(f"{v.name}: the streets join its route points by a {plan:.0f} m path, "
                       f"{plan / max(straight, 1e-9):.1f}x the {straight:.0f} m straight line through them (perhaps a "
                       f"point on a street too narrow to drive, moved to the nearest drivable one); draw the routes "
                       f"with `mmslam scene streets {where} --out routes.png`")
        speed = traj[:, i, 4]
        moving = np.flatnonzero(speed != 0.0)
        last = int(moving[-1]) + 1 if len(moving) else 0  # the first step of the trailing stop
        n_stop = traj.shape[0] - last
        if n_stop >= max(2.0, STOP_SHARE * traj.shape[0]) and float(v.initial_state[4]) > 0.0:
            out.append(f"{v.name}: reaches the end of its route at step {last} and stands still for its last "
                       f"{n_stop} of {traj.shape[0]} steps, about {float(v.initial_state[4]) * scn.dt * n_stop:.0f} m of "
                       f"its drive at {float(v.initial_state[4]):g} m/s; extend its route by at least that")
    return out

