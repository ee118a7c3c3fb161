"""A step without measurements is still a PHD correction (paper eq. (5) with an empty set): every
detectable Gaussian was missed, so its weight becomes (1 - p_D) w with unchanged moments, Gaussians
outside the FOV keep their weight, and the particle weights do not change (an empty product)."""
from __future__ import annotations

import numpy as np

from mmslam.model import VA, VS
from mmslam.scenes.scenario import load_preset
from mmslam.slam.core.gm import GM
from mmslam.slam.filter.local_filter import LocalFilter


def test_empty_measurement_set_applies_the_missed_detection_term():
    scn = load_preset("paper")
    s0 = np.array([20.0, 5.0, 1.5, 0.3, 10.0, 0.0, 0.5])

    def pd_fn(u, x, t):  # 0.9 within 30 m of the vehicle, 0 beyond (VS); VAs always 0.2
        d = np.linalg.norm(np.asarray(x) - np.asarray(u), axis=-1)
        return np.where(d < 30.0, 0.9, 0.0) if t == VS else np.full(d.shape, 0.2)

    f = LocalFilter(scn, "cm1", 3, s0, np.eye(5), 1e-3, pd_fn, np.random.default_rng(0))
    m_vs = np.zeros((3, 2, 7))
    m_vs[:, 0, :3] = s0[:3] + [10.0, 0.0, 0.0]  # inside the FOV
    m_vs[:, 1, :3] = s0[:3] + [100.0, 0.0, 0.0]  # outside
    P_vs = np.broadcast_to(np.eye(7), (3, 2, 7, 7)).copy()
    f.maps[VS] = GM(np.tile([0.5, 0.4], (3, 1)), m_vs, P_vs, np.ones((3, 2), bool))
    f.maps[VA] = GM(np.full((3, 1), 0.8), np.tile([50.0, 60.0, 10.0], (3, 1, 1)),
                    np.broadcast_to(np.eye(3), (3, 1, 3, 3)).copy(), np.ones((3, 1), bool))
    logw = f.logw.copy()
    f.correct(np.zeros((0, 5)))
    np.testing.assert_allclose(f.maps[VS].w, np.tile([0.05, 0.4], (3, 1)), rtol=1e-12)  # 0.1 x 0.5; 0.4 kept
    np.testing.assert_allclose(f.maps[VS].m, m_vs, rtol=0, atol=0)
    np.testing.assert_allclose(f.maps[VA].w, np.full((3, 1), 0.64), rtol=1e-12)  # 0.8 x 0.8
    np.testing.assert_array_equal(f.logw, logw)
