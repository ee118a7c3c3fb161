"""The filter's height process noise from the road's slope (``filter.height_process``, docs/city-slam.md)."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from mmslam.errors import MmslamError
from mmslam.raytrace.analytic import AnalyticSource
from mmslam.scenes.scenario import Vehicle, load_preset, with_overrides
from mmslam.scenes.trajectory import route_height_step, true_trajectories
from mmslam.slam.filter.local_filter import LocalFilter
from mmslam.slam.filter.run import run_filter, vehicle_process_std


def _car(name: str, wps: list[list[float]], speed: float) -> Vehicle:
    x0, y0 = wps[0][:2]
    z0 = wps[0][2] if len(wps[0]) == 3 else 1.6
    return Vehicle(name, (x0, y0, z0, 0.0, speed, 0.0, 300.0), motion="waypoints",
                   waypoints=tuple(tuple(float(c) for c in p) for p in wps))


def test_route_height_step_by_hand():
    # 10 m at a 10% grade, then 10 m flat; 4 m/s, 0.5 s: 2 m per step, at most 0.2 m up in one step
    v = _car("a", [[0, 0, 0], [10, 0, 1], [20, 0, 1]], 4.0)
    assert route_height_step(v, 0.5) == pytest.approx(0.2, rel=1e-12)
    # 10 m per step over a 4 m rise in 8 m, then a 2 m fall in 4 m: the window [0, 10] gives the most, 4 - 1 = 3 m
    v = _car("b", [[0, 0, 0], [8, 0, 4], [12, 0, 2], [40, 0, 2]], 10.0)
    z = lambda s: np.interp(s, [0, 8, 12, 40], [0, 4, 2, 2])  # noqa: E731
    brute = max(abs(z(s + 10.0) - z(s)) for s in np.linspace(0, 30, 30001))
    assert route_height_step(v, 1.0) == pytest.approx(brute, rel=1e-9) == pytest.approx(3.0, rel=1e-12)
    # downhill counts like uphill; a diagonal leg's plan length is its horizontal length (50 m, -5 m)
    assert route_height_step(_car("c", [[0, 0, 5], [30, 40, 0]], 10.0), 1.0) == pytest.approx(1.0, rel=1e-12)
    assert route_height_step(_car("d", [[0, 0, 5], [3, 4, 4.5]], 10.0), 1.0) == pytest.approx(0.5, rel=1e-12)  # shorter than a step
    assert route_height_step(_car("e", [[0, 0], [50, 0]], 7.0), 0.5) == 0.0  # [x, y] waypoints: flat
    assert route_height_step(_car("f", [[0, 0, 2], [50, 0, 2]], 7.0), 0.5) == 0.0
    assert route_height_step(Vehicle("g", (0, 0, 0, 0, 5, 0.1, 0)), 0.5) == 0.0  # ct: a planar turn


def _hill_scenario(**over: str):
    """``paper``'s BS and walls, two cars on straight streets at a 5% grade (0.175 m per step), up and down."""
    scn = load_preset("paper")
    cars = (_car("up", [[-80, 30, 1.6], [80, 30, 9.6]], 7.0), _car("down", [[80, -30, 9.6], [-80, -30, 1.6]], 7.0))
    scn = dataclasses.replace(scn, vehicles=cars)
    return with_overrides(scn, [f"{k}={v}" for k, v in over.items()])


def test_vehicle_process_std_takes_the_larger_of_the_sensor_and_the_slope():
    scn = _hill_scenario()
    base = np.asarray(scn.sensor.vehicle_noise_std)
    got = vehicle_process_std(scn)
    np.testing.assert_allclose(got[:, 2], 0.05 * 7.0 * 0.5, rtol=1e-12)
    exact = base.copy()  # waypoint cars drive their motion model exactly: x, y, heading from filter.motion_jitter_std
    exact[[0, 1, 3]] = np.asarray(scn.filter.motion_jitter_std)[[0, 0, 1]]
    np.testing.assert_array_equal(np.delete(got, 2, axis=1), np.tile(np.delete(exact, 2), (2, 1)))
    np.testing.assert_array_equal(vehicle_process_std(_hill_scenario(**{"filter.height_process": "sensor"})),
                                  np.tile(exact, (2, 1)))
    big = _hill_scenario(**{"sensor.vehicle_noise_std": "[0.2, 0.2, 0.5, 0.001, 0, 0, 0.2]"})
    np.testing.assert_allclose(vehicle_process_std(big)[:, 2], 0.5)
    for name in ("paper", "street", "canyon", "munich"):  # flat: no height noise beyond the sensor's
        flat = load_preset(name)
        np.testing.assert_array_equal(vehicle_process_std(flat)[:, 2], flat.sensor.vehicle_noise_std[2])


def test_local_filter_propagates_with_its_own_process_std():
    scn = with_overrides(load_preset("paper"), ["filter.prior_std=[0, 0, 0, 0, 0, 0, 0]"])
    std = np.array([0.0, 0.0, 0.3, 0.0, 0.0, 0.0, 0.0])
    f = LocalFilter(scn, "odometry", 4000, np.array([0, 0, 0, 0, 5.0, 0, 0]), np.eye(5), 0.0,
                    lambda u, x, t: np.ones(np.broadcast_shapes(u.shape[:-1], x.shape[:-1])),
                    np.random.default_rng(3), measurement_update=False, process_std=std)
    for _ in range(4):
        f.predict(5.0, 0.0)
    assert np.std(f.s[:, 2]) == pytest.approx(0.3 * 2.0, rel=0.05)  # 4 steps: sqrt(4) 0.3; 4000 draws: 1.1% sd
    assert np.ptp(f.s[:, [0, 1, 3, 6]], axis=0).max() == 0.0  # no other noise was drawn
    with pytest.raises(MmslamError, match=r"process_std=.*expected 7 stds >= 0"):
        LocalFilter(scn, "odometry", 2, np.zeros(7), np.eye(5), 0.0, lambda u, x, t: u[..., 0],
                    np.random.default_rng(0), measurement_update=False, process_std=np.full(7, -1.0))


def test_cars_on_a_hill_are_localised_in_height_with_the_route_noise():
    """Paired over seeds: with the motion model's constant height (``sensor``) the height error grows to the
    climb (7 m over 40 steps); with the route's slope noise the measurements keep it to about 1 m."""
    scn = _hill_scenario()
    states = true_trajectories(scn)
    assert np.ptp(states[:, 0, 2]) == pytest.approx(0.175 * 39, rel=1e-9)  # it does climb
    src = AnalyticSource(scn)
    parts = [src.trace_step(k, states[k]) for k in range(scn.steps)]
    paths = {c: np.concatenate([p[c] for p in parts]) for c in parts[0]}
    flat = with_overrides(scn, ["filter.height_process=sensor"])

    def z_rmse(s, seed):
        v = run_filter(s, states, paths, "proposed", 100, seed=seed).vehicles
        late = v["step"] >= 10
        return float(np.sqrt(np.mean((v["z"] - v["true_z"])[late] ** 2)))

    route = np.array([z_rmse(scn, seed) for seed in (0, 1, 2)])
    const = np.array([z_rmse(flat, seed) for seed in (0, 1, 2)])
    assert (const > 2.0).all()  # the climb of k >= 10 is 1.75-6.8 m, never followed
    assert (route < 0.3 * const).all()  # 0.85-1.09 m (paper's r_scale 9: its angles are 0.03 rad, ~2 m in height)


def test_a_very_slow_car_is_not_driven_for_millions_of_steps():
    """A 10% grade at 1e-6 m/s and dt 1 s: 1e-7 m per step (the route's 1e8 steps are not driven: at most
    MAX_DRIVEN_STEPS); a car of speed 0 (built in code: a file refuses it) climbs nothing."""
    from mmslam.scenes.trajectory import MAX_DRIVEN_STEPS

    assert MAX_DRIVEN_STEPS <= 100_000
    assert route_height_step(_car("slow", [[0, 0, 0], [100, 0, 10]], 1e-6), 1.0) == pytest.approx(1e-7, rel=1e-9)
    assert route_height_step(_car("stopped", [[0, 0, 0], [100, 0, 10]], 0.0), 1.0) == 0.0
