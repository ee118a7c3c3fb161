"""Noisy odometry (``sensor.odometry_noise_std``): the speed and turn rate the filter takes as its known inputs."""
from __future__ import annotations

import numpy as np
import pytest

from mmslam.raytrace.analytic import AnalyticSource
from mmslam.scenes.scenario import load_preset, with_overrides
from mmslam.scenes.trajectory import true_trajectories
from mmslam.slam.filter.run import run_filter, vehicle_process_std
from mmslam.slam.sim.sensor import odometry_readings


def test_odometry_readings_are_the_true_inputs_plus_white_noise():
    """20 000 draws: the readings' errors have the stated stds (1% of sd at 2.2 sigma) and no mean; a stopped car
    reads speed 0 exactly and the turn rate's noise; a slow car reads 0 where the noise would make its speed
    negative (P(N(0.02, 0.1) < 0) = 0.42); the true states are not touched."""
    states = np.zeros((10000, 2, 7))
    states[:, 0, 4], states[:, 0, 5] = 7.0, 0.1
    before = states.copy()
    got = odometry_readings(states, (0.1, 0.01), np.random.default_rng(0))
    assert got.shape == (10000, 2, 2)
    err = got[:, 0] - np.array([7.0, 0.1])
    assert np.std(err, axis=0) == pytest.approx([0.1, 0.01], rel=0.03)
    assert np.abs(err.mean(axis=0)).max() < 3 * 0.1 / 100
    assert (got[:, 1, 0] == 0.0).all() and np.std(got[:, 1, 1]) == pytest.approx(0.01, rel=0.03)
    np.testing.assert_array_equal(states, before)
    slow = np.zeros((10000, 1, 7))
    slow[..., 4] = 0.02  # the shortened last step of a route: about 42% of its draws fall below 0
    s = odometry_readings(slow, (0.1, 0.01), np.random.default_rng(1))[..., 0]
    assert s.min() == 0.0 and np.mean(s == 0.0) == pytest.approx(0.42, abs=0.02)


def test_the_filter_process_noise_grows_by_one_step_of_odometry_error():
    """x, y: hypot(0.2, 0.1 m/s x 0.5 s) = 0.20616 m; heading: hypot(0.001, 0.01 rad/s x 0.5 s) = 0.0050990 rad; the
    other entries as the sensor's; [0, 0] (the default) leaves every entry as before."""
    scn = load_preset("paper")
    noisy = with_overrides(scn, ["sensor.odometry_noise_std=[0.1, 0.01]"])
    got = vehicle_process_std(noisy)
    np.testing.assert_allclose(got[:, 0:2], np.hypot(0.2, 0.05), rtol=1e-12)
    np.testing.assert_allclose(got[:, 3], np.hypot(1e-3, 5e-3), rtol=1e-12)
    np.testing.assert_array_equal(got[:, [2, 4, 5, 6]], np.tile(np.asarray(scn.sensor.vehicle_noise_std)[[2, 4, 5, 6]],
                                                              (len(scn.vehicles), 1)))
    np.testing.assert_array_equal(vehicle_process_std(scn), np.tile(scn.sensor.vehicle_noise_std, (len(scn.vehicles), 1)))


def test_a_car_that_drives_its_motion_model_exactly_gets_the_jitter_not_the_sensor_process_noise():
    """The process noise describes how the truth departs from the CT model under the filter's inputs: a ct car with
    sensor.true_process_noise (paper) gets sensor.vehicle_noise_std; a waypoint car (driven by pure pursuit under the
    model), or a ct car without true process noise, filter.motion_jitter_std (x, y 0.1 m, heading 0.001 rad by
    default), grown by the odometry's error: hypot(0.1, 0.1 m/s x 0.5 s) = 0.111803 m, hypot(0.001, 0.005) rad."""
    from mmslam.slam.filter.run import truth_has_process_noise

    paper = load_preset("paper")
    assert paper.sensor.true_process_noise and all(v.motion == "ct" for v in paper.vehicles)
    assert all(truth_has_process_noise(paper, n) for n in range(len(paper.vehicles)))
    quiet = with_overrides(paper, ["sensor.true_process_noise=false"])
    assert not any(truth_has_process_noise(quiet, n) for n in range(len(quiet.vehicles)))
    got = vehicle_process_std(quiet)
    assert quiet.filter.motion_jitter_std == (0.1, 1e-3)
    np.testing.assert_array_equal(got[:, [0, 1, 3]], np.tile([0.1, 0.1, 1e-3], (len(quiet.vehicles), 1)))
    np.testing.assert_array_equal(got[:, [2, 4, 5, 6]], vehicle_process_std(paper)[:, [2, 4, 5, 6]])
    munich = with_overrides(load_preset("munich"), ["sensor.odometry_noise_std=[0.1, 0.01]",
                                                    "sensor.true_process_noise=true"])  # waypoint cars: no noise drawn
    got = vehicle_process_std(munich)
    np.testing.assert_allclose(got[:, 0:2], 0.11180339887498949, rtol=1e-12)
    np.testing.assert_allclose(got[:, 3], np.hypot(1e-3, 5e-3), rtol=1e-12)
    np.testing.assert_array_equal(got[:, 6], munich.sensor.vehicle_noise_std[6])  # the clock's random walk: the sensor's
    np.testing.assert_array_equal(vehicle_process_std(with_overrides(munich, ["filter.motion_jitter_std=[0.3, 0.02]"]))
                                  [:, [0, 3]], np.tile([np.hypot(0.3, 0.05), np.hypot(0.02, 5e-3)], (5, 1)))


def test_the_rule_is_per_car_in_a_scenario_of_ct_and_waypoint_cars():
    """paper with its second car on a route (true_process_noise on): the ct car's truth carries the noise (and the
    filter takes 0.2 m), the waypoint car's does not (0.1 m); the trajectories agree: only the ct car's truth moves
    when the noise is switched off."""
    import dataclasses

    from mmslam.scenes.trajectory import true_trajectories as truth
    from mmslam.slam.filter.run import truth_has_process_noise

    paper = load_preset("paper")
    v0, v1 = paper.vehicles[0], paper.vehicles[1]
    route = dataclasses.replace(v1, motion="waypoints",
                                waypoints=((float(v1.initial_state[0]), float(v1.initial_state[1])),
                                           (float(v1.initial_state[0]) + 100.0, float(v1.initial_state[1]))))
    mixed = dataclasses.replace(paper, vehicles=(v0, route))
    assert [truth_has_process_noise(mixed, n) for n in range(2)] == [True, False]
    np.testing.assert_array_equal(vehicle_process_std(mixed)[:, [0, 1, 3]], [[0.2, 0.2, 1e-3], [0.1, 0.1, 1e-3]])
    quiet = with_overrides(mixed, ["sensor.true_process_noise=false"])
    a, b = truth(mixed, 10), truth(quiet, 10)
    assert np.abs(a[:, 0, 0:2] - b[:, 0, 0:2]).max() > 0.1  # the ct car's truth carries the noise
    np.testing.assert_array_equal(a[:, 1], b[:, 1])  # the route car's does not


def test_the_filter_takes_the_readings_of_the_run_odometry_stream():
    """Each vehicle's known inputs of step k - 1 are the readings of the run's odometry stream (the last child of the
    seed's SeedSequence, recomputed here by hand); with exact odometry they are the true inputs, and dead reckoning
    with no process, jitter or prior noise stays on the truth (1e-9 m), while with noisy odometry it drifts from it."""
    from mmslam.slam.filter.run import CooperativeRun

    zero = "[0, 0, 0, 0, 0, 0, 0]"
    scn = with_overrides(load_preset("paper"), [f"sensor.vehicle_noise_std={zero}", f"filter.prior_std={zero}",
                                                "filter.motion_jitter_std=[0, 0]", "sensor.odometry_noise_std=[0.5, 0.05]"])
    steps = 12
    states = true_trajectories(scn, steps)
    src = AnalyticSource(scn)
    parts = [src.trace_step(k, states[k]) for k in range(steps)]
    paths = {c: np.concatenate([p[c] for p in parts]) for c in parts[0]}
    n_veh = states.shape[1]
    odo = odometry_readings(states, (0.5, 0.05), np.random.default_rng(np.random.SeedSequence(5).spawn(3 + n_veh)[-1]))
    run = CooperativeRun(scn, states, paths, "odometry", 3, 5, evaluate=False)
    for k in range(1, steps):
        for n in range(n_veh):
            _, spd, tr, _ = run.local_inputs(k, n)
            assert (spd, tr) == (odo[k - 1, n, 0], odo[k - 1, n, 1])
    assert run.local_inputs(0, 0)[1:3] == (None, None)
    exact_scn = with_overrides(scn, ["sensor.odometry_noise_std=[0, 0]"])
    exact = CooperativeRun(exact_scn, states, paths, "odometry", 3, 5, evaluate=False)
    assert exact.local_inputs(3, 1)[1:3] == (states[2, 1, 4], states[2, 1, 5])
    assert np.asarray(run_filter(exact_scn, states, paths, "odometry", 3, seed=5).vehicles["pos_err"]).max() < 1e-9
    assert np.asarray(run_filter(scn, states, paths, "odometry", 3, seed=5).vehicles["pos_err"]).max() > 0.5


def test_mmslam_slam_says_in_one_line_which_cars_take_the_jitter(tmp_path):
    """run_slam's notice (what ``mmslam slam`` prints): on a cache whose cars drive the CT model exactly (paper
    traced with sensor.true_process_noise off) one line names how many cars and the x, y and heading noise they get,
    the jitter's 0.1 m and 0.001 rad, and the run's meta holds the same per car; on paper as published (its truth
    carries the noise) no such line."""
    from mmslam.raytrace.cache import load_cache
    from mmslam.raytrace.trace import trace_scenario
    from mmslam.slam.filter.run import run_slam

    out = {}
    for name, sets in (("quiet", ["sensor.true_process_noise=false"]), ("paper", [])):
        scn = with_overrides(load_preset("paper"), sets)
        d = trace_scenario(scn, AnalyticSource(scn), tmp_path / name, steps=3, progress=False)
        said: list[str] = []
        r = run_slam(load_cache(d).path, "odometry", particles=5, seed=0, compile_notice=said.append)
        out[name] = ([s for s in said if s.startswith("process noise of the")], r.meta)
    lines, meta = out["quiet"]
    n = len(load_preset("paper").vehicles)
    assert lines == [f"process noise of the {n} car(s) whose truth drives the motion model exactly: x, y 0.1 m, "
                     "heading 0.001 rad per step (filter.motion_jitter_std with the odometry's error; "
                     "sensor.vehicle_noise_std only where sensor.true_process_noise gives a ct car's truth that noise)"]
    assert meta["exact_truth"] == [True] * n
    np.testing.assert_array_equal(np.asarray(meta["process_std"])[:, [0, 1, 3]], np.tile([0.1, 0.1, 1e-3], (n, 1)))
    lines, meta = out["paper"]
    assert lines == [] and meta["exact_truth"] == [False] * n


def test_a_component_the_noisy_truth_drives_exactly_takes_the_jitter():
    """A ct car with sensor.true_process_noise whose x, y entries are 0 draws no x, y noise in its truth: the filter
    gives those the jitter (0.1 m), not 0 (a particle cloud that never spreads), and keeps the sensor's heading
    noise (3e-3 rad); with the heading entry 0 as well, the heading takes the jitter's 0.001 rad."""
    from mmslam.model import vehicle_ct

    paper = load_preset("paper")
    xy0 = with_overrides(paper, ["sensor.vehicle_noise_std=[0, 0, 0, 3e-3, 0, 0, 0.2]"])
    truth = true_trajectories(xy0, 6)  # x, y: the CT model's step exactly; heading: noise drawn
    step = np.array([[vehicle_ct(truth[k - 1, n], xy0.dt) for n in range(truth.shape[1])] for k in range(1, 6)])
    np.testing.assert_allclose(truth[1:, :, 0:2], step[..., 0:2], rtol=0, atol=1e-12)
    assert np.abs(truth[1:, :, 3] - step[..., 3]).max() > 1e-4
    got = vehicle_process_std(xy0)
    np.testing.assert_array_equal(got[:, [0, 1, 3, 6]], np.tile([0.1, 0.1, 3e-3, 0.2], (len(paper.vehicles), 1)))
    h0 = with_overrides(paper, ["sensor.vehicle_noise_std=[0, 0, 0, 0, 0, 0, 0.2]"])
    np.testing.assert_array_equal(vehicle_process_std(h0)[:, [0, 1, 3]], np.tile([0.1, 0.1, 1e-3], (len(paper.vehicles), 1)))
    np.testing.assert_array_equal(vehicle_process_std(paper)[:, [0, 1, 3]], np.tile([0.2, 0.2, 1e-3], (len(paper.vehicles), 1)))
