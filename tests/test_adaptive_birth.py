"""The adaptive birth (``filter.adaptive_birth``, Ristic, Clark, Vo & Vo 2012): the birth of a measurement ``z_j`` in
particle ``p`` has weight ``birth_weight x c(z_j) / psi_p(z_j)``, the share of ``z_j`` that neither the particle's maps
nor the BS explained at the correction that saw it (``slam/filter/local_filter.py``)."""
from __future__ import annotations

import numpy as np

import mmslam.slam.filter.local_filter as lf
from mmslam.model import SP, VA, Bounce
from mmslam.scenes.scenario import load_preset, with_overrides
from mmslam.slam.filter.local_filter import LocalFilter
from mmslam.slam.models.measurement import measure

STATE = np.array([5.0, -20.0, 1.5, 0.3, 10.0, 0.0, 2.0])
R = np.diag([0.1, 1e-4, 1e-4, 1e-4, 1e-4])


def _pd(p):
    return lambda u, x, t: np.full(np.shape(x)[:-1], p)


def _filter(adaptive: bool, clutter: float = 1e-3, particles: int = 4) -> LocalFilter:
    scn = with_overrides(load_preset("paper"), [f"filter.adaptive_birth={'true' if adaptive else 'false'}"])
    return LocalFilter(scn, "cm1", particles, STATE, R, clutter, _pd(0.9), np.random.default_rng(7), vehicle=1)


def _scan(scn) -> np.ndarray:
    """Two measurements: the BS's line of sight and a wall's image source 40 m off (no map explains it)."""
    bs = np.asarray(scn.bs, float)
    return np.stack([measure(STATE, bs, Bounce.DIRECT, bs), measure(STATE, bs + [30.0, -40.0, 0.0], Bounce.MIRROR, bs)])


def test_a_measurement_the_bs_explains_births_light_and_an_unexplained_one_at_the_full_weight():
    """Same seed, same particles: after one scan (empty maps) each birth's weight is the plain filter's times
    ``c / psi_p(z_j)``; the line of sight, which the BS explains (p_D 0.9), gets a share below 1e-3, the wall's
    path, which nothing explains, a share of 1; the plain filter keeps no share."""
    plain, adaptive = _filter(False), _filter(True)
    Z = _scan(plain.scn)
    for f in (plain, adaptive):
        f.step(Z)
    assert plain._unexplained is None
    share = adaptive._unexplained
    assert share.shape == (4, 2)
    assert (share[:, 0] < 1e-3).all() and np.allclose(share[:, 1], 1.0, rtol=0.0, atol=1e-12)
    np.testing.assert_array_equal(adaptive.s, plain.s)
    for f in (plain, adaptive):
        f.predict(10.0, 0.0)
    np.testing.assert_array_equal(adaptive.s, plain.s)
    a, p = adaptive.maps[VA], plain.maps[VA]  # a VA birth of each measurement
    assert a.capacity == p.capacity == 2 and p.mask.all() and a.mask.all()
    np.testing.assert_array_equal(a.m, p.m)
    np.testing.assert_allclose(a.w, p.w * share, rtol=1e-12, atol=0.0)
    assert np.all(p.w == plain.fp.birth_weight)
    a, p = adaptive.maps[SP], plain.maps[SP]  # the SP births inside the FOV (one measurement's): the same rule
    assert a.capacity == p.capacity == 1
    np.testing.assert_array_equal(a.m, p.m)
    assert any(np.allclose(a.w[:, 0], p.w[:, 0] * share[:, j], rtol=1e-12, atol=0.0) for j in range(2))


def test_resampling_takes_each_particles_share_along():
    """The shares are per particle: a resampling with indices ``idx`` leaves ``share[idx]``."""
    f = _filter(True)
    f.step(_scan(f.scn))
    before = f._unexplained.copy()
    idx = np.array([3, 3, 0, 1])
    orig = lf.systematic_resample
    lf.systematic_resample = lambda w, rng: idx
    try:
        _, resampled = f.resample(np.array([0.97, 0.01, 0.01, 0.01]))
    finally:
        lf.systematic_resample = orig
    assert resampled
    np.testing.assert_array_equal(f._unexplained, before[idx])


def test_without_clutter_every_measurement_births_at_the_full_weight():
    """Without a clutter term ``c / psi`` is 0 for every measurement: the option then leaves the plain birth (the
    filter says so in ``adaptive_birth``), and the births equal the plain filter's."""
    plain, adaptive = _filter(False, clutter=0.0), _filter(True, clutter=0.0)
    assert adaptive.fp.adaptive_birth and not adaptive.adaptive_birth and _filter(True).adaptive_birth
    Z = _scan(plain.scn)
    for f in (plain, adaptive):
        f.step(Z)
        f.predict(10.0, 0.0)
    assert adaptive._unexplained is None
    np.testing.assert_array_equal(adaptive.maps[VA].w, plain.maps[VA].w)


def test_mmslam_slam_says_in_one_line_when_no_clutter_leaves_the_plain_birth(tmp_path):
    """run_slam's notice (what ``mmslam slam`` prints) on a paper cache with the adaptive birth on: with
    ``sensor.clutter_mean = 0`` one line says every measurement births at the full weight, and the meta records the
    birth as not adaptive; with clutter, no such line and an adaptive birth; the odometry reference, which births
    nothing, no line."""
    from mmslam.raytrace.analytic import AnalyticSource
    from mmslam.raytrace.cache import load_cache
    from mmslam.raytrace.trace import trace_scenario
    from mmslam.slam.filter.run import run_slam

    scn = load_preset("paper")
    path = load_cache(trace_scenario(scn, AnalyticSource(scn), tmp_path, steps=3, progress=False)).path
    for variant, clutter, lines, adaptive in (("proposed", "0", 1, False), ("proposed", "1", 0, True),
                                              ("odometry", "0", 0, False)):  # dead reckoning births nothing
        said: list[str] = []
        r = run_slam(path, variant, particles=5, seed=0, compile_notice=said.append,
                     overrides=["filter.adaptive_birth=true", f"sensor.clutter_mean={clutter}"])
        assert len([s for s in said if s.startswith("filter.adaptive_birth: no clutter")]) == lines
        assert r.meta["adaptive_birth"] is adaptive
