"""The car a vehicle scatterer (VS) is, for the VS spec of :mod:`mmslam.slam.specs.landmarks` (issue 22,
docs/city-slam.md "Vehicles as extended scatterers"): its body, where a VS may be born and where a VS Gaussian
may stay.

- :func:`vs_body`: the body a VS path bounces off (``filter.vs_body_model``, ``filter.vs_body``), handed to
  the VS likelihood (:func:`mmslam.slam.phd.ckf.ckf_update`);
- :func:`vs_birth_moments`: a VS birth from a bounce point within ``filter.vs_birth_height`` of the receiving
  antenna, placed at the antenna behind the bounce;
- :func:`vs_on_road`: the VS Gaussians a prediction keeps (on the road band near the vehicle, and the other cars'
  own estimates wherever they stand).
"""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from ..core.gm import NO_LABEL, GM, is_ego_label
from ..models.vs import body_antennas

if TYPE_CHECKING:
    from mmslam.scenes.scenario import Scenario

Moments = tuple[np.ndarray, np.ndarray, np.ndarray]
"""``(mean (P, J, 3), cov (P, J, 3, 3), ok (P, J))`` of a birth inversion (m, m^2, valid)."""


def vs_body(scn: "Scenario") -> np.ndarray | None:
    """``(4,)`` car body ``filter.vs_body`` ``[length, width, height, depth]`` (m) of a VS under
    ``filter.vs_body_model = "ellipsoid"``, else None (a point VS; ``auto`` is resolved by the run from its
    path source, :func:`mmslam.slam.filter.run.resolve_vs_body`)."""
    fp = scn.filter
    body = np.asarray(fp.vs_body, float)
    return body if fp.vs_body_model == "ellipsoid" and body[0] > 0.0 else None


def vs_birth_moments(states: np.ndarray, moments: Moments, scn: "Scenario") -> Moments:
    """The birth moments of a VS from the inversion of a SCATTER path, which gives where the path bounced.

    - A birth whose bounce point lies more than ``filter.vs_birth_height`` (m) above or below the receiving
      antenna (``states (P, 7)``, per particle) is invalid: a car is on the road, a wall reflection off a
      roof-top BS bounces 3-15 m up.
    - With a body (:func:`vs_body`) the mean moves to the antenna behind the bounce
      (:func:`mmslam.slam.models.vs.body_antennas`: the heading is not known at birth, so the body is averaged
      over headings) and the position covariance is widened by ``diag(e^2, e^2, 0)``, ``e = (length - width) / 4``
      (m): half the difference of the horizontal semi-axes, what the unknown heading leaves open.
    """
    s = np.asarray(states, float)
    mean, cov, ok = moments
    ok = ok & (np.abs(mean[..., 2] - s[:, None, 2]) <= scn.filter.vs_birth_height)
    body = vs_body(scn)
    if body is not None:
        mean = body_antennas(mean, s[:, None, 0:3], scn.bs_array, body)
        e2 = ((body[0] - body[1]) / 4.0) ** 2
        cov = np.array(cov, float, copy=True)
        cov[..., 0, 0] += e2
        cov[..., 1, 1] += e2
    return mean, cov, ok


def vs_on_road(g: GM, states: np.ndarray, scn: "Scenario") -> GM:
    """The predicted VS map of each particle without the Gaussians that cannot be a car: those within the sensor's
    range (``sensor.fov_range``, horizontally) whose antenna height differs from the particle's by more than
    ``filter.vs_birth_height`` (m): a VS born at a low wall reflection follows the specular point up the wall
    as the vehicle moves. A car's own estimate (a Gaussian with its :func:`~mmslam.slam.core.gm.ego_label`: another
    car's, which the fused map downlinks, eq. (11); the receiver's own, where it is kept, stands at its antenna) is a
    car wherever it stands and stays (``filter.vs_keep_cars``; without labels no Gaussian is known as one): on sf5's
    hills another car within 50 m stands up to 4.7 m above or below the antenna, and without it the paths off its
    body birth false VAs (docs/city-slam.md, "Cars up the hill"). ``g`` batch ``(P,)``, ``states (P, 7)``; removed
    slots are masked (weight 0, mean 0, covariance I, label :data:`~mmslam.slam.core.gm.NO_LABEL`)."""
    if not g.capacity:
        return g
    s = np.asarray(states, float)[:, None, :]
    dz = np.abs(g.m[..., 2] - s[..., 2])
    near = np.hypot(g.m[..., 0] - s[..., 0], g.m[..., 1] - s[..., 1]) <= scn.sensor.fov_range
    off = g.mask & near & (dz > scn.filter.vs_birth_height)
    if g.label is not None and scn.filter.vs_keep_cars:
        off &= ~is_ego_label(g.label)
    if not off.any():
        return g
    out = g.copy()
    out.mask[off] = False
    out.w[off] = 0.0
    out.m[off] = 0.0
    out.P[off] = np.eye(g.dim)
    if out.label is not None:  # a masked slot has no identity
        out.label[off] = NO_LABEL
    return out
