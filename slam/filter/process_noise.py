"""The filter's process noise per vehicle: how its truth departs from the CT model (paper eq. (1)) per step.

A ``ct`` car with ``sensor.true_process_noise`` carries ``sensor.vehicle_noise_std`` in its truth (the paper's
model) and the filter takes the same (but the jitter below in an x, y or heading entry of 0, which that truth
drives exactly); every other car drives the CT model exactly under its true inputs (a
``waypoints`` car by pure pursuit, :mod:`mmslam.scenes.driving`), and the filter takes ``filter.motion_jitter_std``
in x, y and heading (docs/city-slam.md, "The process noise"). Noisy odometry and a hill's slope add to either.
"""
from __future__ import annotations

import numpy as np

from mmslam.scenes.scenario import Scenario


def truth_has_process_noise(scn: Scenario, vehicle: int) -> bool:
    """Whether vehicle ``vehicle``'s true trajectory carries the sensor's process noise: a ``ct`` car with
    ``sensor.true_process_noise`` (the paper's model; :func:`~mmslam.scenes.trajectory.true_trajectories`). Every
    other car drives its CT model exactly under its true inputs (a ``waypoints`` car by pure pursuit)."""
    return bool(scn.sensor.true_process_noise) and scn.vehicles[vehicle].motion == "ct"


def vehicle_process_std(scn: Scenario) -> np.ndarray:
    """The filter's process noise std of every vehicle, ``(n_veh, 7)`` (units of ``sensor.vehicle_noise_std``).

    The departure of the vehicle's truth from the CT model (eq. 1) under the inputs the filter reads, per step:

    - x, y and heading: ``sensor.vehicle_noise_std`` where the truth carries that process noise
      (:func:`truth_has_process_noise`: the paper's model, and that entry is not 0), else
      ``filter.motion_jitter_std`` (the truth drives the model exactly in that component: a small noise that keeps
      the particle cloud diverse); either grown by one step's error
      of the odometry (``sensor.odometry_noise_std`` times ``dt``, added in quadrature: the speed error along the
      track in either axis, the turn rate's in the heading);
    - height: under ``filter.height_process = "route"`` the larger of ``vehicle_noise_std[2]`` and the largest
      height change over one step's travel along the vehicle's route or in one step of the car driving it
      (:func:`~mmslam.scenes.trajectory.route_height_step`: the road's slope, 0 on flat streets; the motion model
      keeps the height constant, on a hill the car climbs ``grade x speed x dt`` per step), else
      ``vehicle_noise_std[2]``;
    - speed, turn rate, clock bias: ``sensor.vehicle_noise_std`` (the clock bias's random walk is the sensor's,
      in every scene).
    """
    from mmslam.scenes.trajectory import route_height_step

    sensor = np.asarray(scn.sensor.vehicle_noise_std, float)
    jitter = np.asarray(scn.filter.motion_jitter_std, float)
    odo = np.asarray(scn.sensor.odometry_noise_std, float) * float(scn.dt)  # one step's error of the odometry
    out = np.tile(sensor, (len(scn.vehicles), 1))
    for n, v in enumerate(scn.vehicles):
        exact = not truth_has_process_noise(scn, n)
        for i, j in ((0, 0), (1, 0), (3, 1)):  # a component the truth drives exactly (no noise drawn) takes the jitter
            if exact or sensor[i] == 0.0:
                out[n, i] = jitter[j]
        out[n, 0:2] = np.hypot(out[n, 0:2], odo[0])  # the speed error along the track, either axis
        out[n, 3] = np.hypot(out[n, 3], odo[1])  # the turn rate's error in the heading
        if scn.filter.height_process == "route":
            out[n, 2] = max(sensor[2], route_height_step(v, scn.dt))
    return out
