"""The random walk of a static landmark (``filter.types.<T>.drift_std``): ``P + dt drift^2 I`` on the position of
every live Gaussian at each local prediction, nothing else; refused for a moving type."""
from __future__ import annotations

import numpy as np
import pytest

from mmslam.errors import ConfigError
from mmslam.model import SP, VA, VS
from mmslam.scenes.scenario import load_preset, with_overrides
from mmslam.slam.core.gm import GM, random_walk
from mmslam.slam.filter.local_filter import LocalFilter


def test_random_walk_adds_the_variance_to_the_position_of_live_gaussians_only():
    """A 7-dim mixture of two particles, one slot masked: the live slots' x, y, z variances grow by var, nothing
    else moves (off-diagonal and velocity entries, weights, means, labels, Beta p_D; the masked slot keeps I)."""
    rng = np.random.default_rng(1)
    A = rng.normal(size=(2, 3, 7, 7))
    P = A @ np.swapaxes(A, -1, -2) + np.eye(7)
    mask = np.array([[True, False, True], [True, True, True]])
    P[~mask] = np.eye(7)
    g = GM(rng.random((2, 3)), rng.normal(size=(2, 3, 7)), P, mask, np.full((2, 3, 2), 2.0),
           np.arange(6).reshape(2, 3))
    out = random_walk(g, 0.09)
    want = P.copy()
    for b, q in zip(*np.nonzero(mask)):
        want[b, q, 0, 0] += 0.09
        want[b, q, 1, 1] += 0.09
        want[b, q, 2, 2] += 0.09
    np.testing.assert_array_equal(out.P, want)
    np.testing.assert_array_equal(out.P[0, 1], np.eye(7))
    assert out.w is g.w and out.m is g.m and out.pd_beta is g.pd_beta and out.label is g.label
    assert not np.shares_memory(out.P, g.P) and np.array_equal(g.P, P)  # the input is not changed


def _filter(rows: list[str], variant: str = "cm1") -> LocalFilter:
    scn = with_overrides(load_preset("paper"), rows)
    s0 = np.array([20.0, 5.0, 1.5, 0.3, 10.0, 0.0, 0.5])
    pd_fn = lambda u, x, t: np.full(np.broadcast_shapes(np.shape(u)[:-1], np.shape(x)[:-1]), 0.5)  # noqa: E731
    return LocalFilter(scn, variant, 2, s0, np.eye(5), 1e-3, pd_fn, np.random.default_rng(0))


def test_an_unobserved_va_grows_by_n_dt_drift_squared_and_other_types_do_not():
    """drift_std 0.4 m/s^0.5 on VA, dt 0.5 s (paper): after n predictions without measurements a VA's position
    variance is its start plus n 0.5 0.16 = 0.08 n m^2 per axis, its mean and the SP's covariance as they were."""
    f = _filter(["filter.types.VA.drift_std=0.4"])
    assert f.scn.dt == 0.5
    P0 = np.diag([0.3, 0.2, 0.1])
    f.maps[VA] = GM(np.ones((2, 1)), np.tile([50.0, 60.0, 10.0], (2, 1, 1)), np.tile(P0, (2, 1, 1, 1)),
                    np.ones((2, 1), bool))
    f.maps[SP] = GM(np.ones((2, 1)), np.tile([5.0, 6.0, 1.0], (2, 1, 1)), np.tile(P0, (2, 1, 1, 1)),
                    np.ones((2, 1), bool))
    for _ in range(3):
        f.predict(10.0, 0.0)
    np.testing.assert_allclose(f.maps[VA].P[:, 0], np.tile(P0 + 3 * 0.08 * np.eye(3), (2, 1, 1)), rtol=1e-14)
    np.testing.assert_array_equal(f.maps[VA].m[:, 0], np.tile([50.0, 60.0, 10.0], (2, 1)))
    np.testing.assert_array_equal(f.maps[SP].P[:, 0], np.tile(P0, (2, 1, 1)))


def test_drift_zero_is_the_paper_and_a_moving_type_is_refused():
    """paper and twc2020 pin drift_std 0 on VA (their VAs do not move; the default is 0 too); drift_std on the moving VS
    is a one-line ConfigError naming the key and the fix."""
    assert load_preset("paper").filter.type_params("VA").drift_std == 0.0
    assert load_preset("twc2020").filter.type_params("VA").drift_std == 0.0
    assert _filter([])._walk[VA] == 0.0
    for variant in ("cm1", "baseline"):  # also where the variant keeps no VS map
        with pytest.raises(ConfigError, match=r"^filter\.types\.VS\.drift_std: .*set drift_std = 0$"):
            _filter(["filter.types.VS.drift_std=0.1"], variant)
    with pytest.raises(ConfigError, match="drift_std"):
        with_overrides(load_preset("paper"), ["filter.types.VA.drift_std=-1"])
