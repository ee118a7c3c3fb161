"""First-detection landmarks reach the other cars only once confirmed (``slam/filter/confirmation.py``): which births
are new, which are detected since, and what the BS holds back from whom."""
from __future__ import annotations

import numpy as np
import pytest

from mmslam.model import Bounce
from mmslam.scenes.scenario import load_preset, with_overrides
from mmslam.slam.core.gm import GM, LABEL_BITS, empty
from mmslam.slam.filter import FusionCenter
from mmslam.slam.filter.confirmation import Confirmation, Unconfirmed, detected_since_birth, fresh_labels
from mmslam.slam.models.measurement import VA, measure

L0 = (0 << LABEL_BITS) + 5  # a birth of vehicle 0
L1 = (1 << LABEL_BITS) + 3  # a birth of vehicle 1


def _gm(w, m, label, s=0.2):
    n = len(w)
    return GM(np.asarray(w, float), np.asarray(m, float), np.broadcast_to(0.04 * np.eye(3), (n, 3, 3)).copy(),
              np.ones(n, bool), np.tile([s, 1.8], (n, 1)), np.asarray(label, np.int64))


def test_fresh_labels_are_the_birth_slots_weighted_above_the_birth_weight():
    # two particles, three births: slot 0 at the plain weight (times c / psi <= 1) in both; slot 1 new in particle 0;
    # slot 2 new in particle 1 only (0.9 times c / psi = 0.5), masked in particle 0
    w = np.array([[1.5e-5, 0.9, 0.7], [0.75e-5, 1e-9, 0.45]])
    mask = np.array([[True, True, False], [True, True, True]])
    lab = np.where(mask, [10, 11, 12], -1)
    born = GM(w, np.zeros((2, 3, 3)), np.broadcast_to(np.eye(3), (2, 3, 3, 3)).copy(), mask, None, lab)
    assert fresh_labels(born, 1.5e-5).tolist() == [11, 12]  # slot 2's 0.7 sits in a masked slot: not counted
    assert fresh_labels(GM(w, born.m, born.P, mask), 1.5e-5).size == 0  # no labels: nothing to track


def test_detected_since_birth_by_the_beta_count():
    # prior s0 = 0.2 (p_D 0.1, count 2): one detection adds 1; a half of one (a pooled copy) is the bar
    avg = _gm([0.9, 0.8, 0.7, 0.6], np.zeros((4, 3)), [1, 2, 3, 4])
    avg.pd_beta[:, 0] = [0.2, 1.2, 0.69, 0.7]
    assert detected_since_birth(avg, 0.2).tolist() == [2, 4]


def test_the_bs_holds_a_landmark_one_car_saw_once_from_the_others_until_a_second_car_sees_it():
    scn = with_overrides(load_preset("canyon"), ["filter.types.VA.birth_existence=0.9"])
    fc = FusionCenter(scn, "proposed")
    far = np.array([[0.0, 0.0, 1.6]])
    u0, u1, u2 = Unconfirmed(fc.types), Unconfirmed(fc.types), Unconfirmed(fc.types)
    u0.born(VA, np.array([L0]))
    up0 = _gm([0.9], [[10.0, 40.0, 25.0]], [L0])
    down0 = fc.fuse({VA: up0}, far, np.zeros(7), np.eye(7), vehicle=0, unconfirmed=u0)
    assert L0 in down0[VA].label[down0[VA].mask]  # the car that bore it keeps it
    nothing = empty((), 0, 3, with_pd_beta=True, with_label=True)
    down2 = fc.fuse({VA: nothing}, far, np.zeros(7), np.eye(7), vehicle=2, unconfirmed=u2)
    assert not down2[VA].mask.any()  # another car does not get it ...
    assert fc.maps[VA].label[fc.maps[VA].mask].tolist() == [L0]  # ... while the BS map keeps it
    # vehicle 1 sees the same wall once: its own new birth, 5 cm off, is matched with vehicle 0's: confirmed
    u1.born(VA, np.array([L1]))
    down1 = fc.fuse({VA: _gm([0.9], [[10.05, 40.0, 25.0]], [L1])}, far, np.zeros(7), np.eye(7), vehicle=1,
                    unconfirmed=u1)
    assert down1[VA].mask.sum() == 1 and not fc.confirmation.held[VA]
    down2 = fc.fuse({VA: nothing}, far, np.zeros(7), np.eye(7), vehicle=2, unconfirmed=u2)
    assert down2[VA].mask.sum() == 1  # now every car gets it
    # a re-upload by vehicle 0 that still calls L0 unconfirmed does not hold it again
    down0 = fc.fuse({VA: up0}, far, np.zeros(7), np.eye(7), vehicle=0, unconfirmed=u0)
    assert not fc.confirmation.held[VA]


def test_the_car_that_bore_it_releases_it_by_its_second_detection():
    c = Confirmation((VA,))
    u = Unconfirmed((VA,))
    u.born(VA, np.array([L0, L0 + 1]))
    c.upload(VA, 0, u.labels[VA])
    assert c.held[VA] == {L0, L0 + 1}
    g = _gm([0.9, 0.8], [[0.0, 0.0, 0.0], [5.0, 0.0, 0.0]], [L0, L0 + 1])
    assert c.for_vehicle(VA, g, 1).label.tolist() == []
    assert c.for_vehicle(VA, g, 0).label.tolist() == [L0, L0 + 1]
    u.detected(VA, np.array([L0 + 1]))  # detected at a second step (its Beta count rose)
    c.upload(VA, 0, u.labels[VA])
    assert c.for_vehicle(VA, g, 1).label.tolist() == [L0 + 1]
    # vehicle 1's upload leaves vehicle 0's held labels alone
    c.upload(VA, 1, set())
    assert c.held[VA] == {L0}


def _run(scn, Zs, dt, steps_between=None):
    from mmslam.slam.filter.local_filter import LocalFilter

    R = np.diag([0.1, 0.01, 0.01, 0.01, 0.01]) ** 2
    pd = lambda u, x, t: np.full(np.broadcast_shapes(np.shape(u)[:-1], np.shape(x)[:-1]), 0.9)  # noqa: E731
    f = LocalFilter(scn, "proposed", 16, Zs[0][1], R, 1e-3, pd, np.random.default_rng(7), vehicle=1)
    out = []
    for k, (Z, _) in enumerate(Zs):
        f.step(Z) if k == 0 else f.step(Z, 8.0, 0.0)
        out.append(set(f.unconfirmed.labels[VA]))
    return f, out


@pytest.mark.parametrize("seen_again", [False, True])
def test_a_local_filter_confirms_a_wall_at_its_second_detection(seen_again):
    """A car at 8 m/s along heading 0.2 rad passes a wall (the BS mirrored in x = 50): seen at steps 0 and 1 (born
    from step 0 new, its label unconfirmed after step 1 only if step 1 missed it), and at step 2 if ``seen_again``."""
    scn = with_overrides(load_preset("canyon"), ["filter.types.VA.birth_existence=0.9", "filter.adaptive_birth=false"])
    bs = np.asarray(scn.bs, float)
    va = bs * [-1.0, 1.0, 1.0] + [100.0, 0.0, 0.0]
    dt = float(scn.dt)
    states = [np.array([20.0 + 8 * dt * k * np.cos(0.2), 10.0 + 8 * dt * k * np.sin(0.2), 1.5, 0.2, 8.0, 0.0, 0.0])
              for k in range(4)]
    seen = [True, False, seen_again, False]
    Zs = [(np.stack([measure(s, bs, int(Bounce.DIRECT), bs)] + ([measure(s, va, int(Bounce.MIRROR), bs)] if v else [])),
           s) for s, v in zip(states, seen)]
    f, out = _run(scn, Zs, dt)
    assert out[0] == set()  # no birth at the first step
    born = out[1]
    assert len(born) >= 1 and all(x >> LABEL_BITS == 1 for x in born)  # vehicle 1's labels
    if seen_again:
        assert not (born & out[2])  # detected at step 2: confirmed
    else:
        assert born <= out[3]  # never seen again: still unconfirmed


def test_a_held_landmark_that_the_fused_reduction_merges_another_into_is_confirmed():
    """Vehicle 1's landmark M (0.6, x = 10.2) is shared; vehicle 0 uploads its copy of M (x = 10.0) and a new L (0.9,
    x = 10.55, 0.35 m from M: apart in vehicle 0's own map, whose gate of 6 at 0.04 I m^2 is 0.49 m). At the BS M's pair
    is merged first (x ~ 10.1), then the gate merges it into the heavier L, whose label the result keeps: L took M in,
    so L is confirmed and every car still gets the landmark (it used to vanish from vehicles 1's and 2's downlinks)."""
    scn = load_preset("canyon")
    fc = FusionCenter(scn, "proposed")
    far = np.array([[0.0, 0.0, 1.6]])
    nothing = empty((), 0, 3, with_pd_beta=True, with_label=True)
    u0, u1, u2 = Unconfirmed(fc.types), Unconfirmed(fc.types), Unconfirmed(fc.types)
    fc.fuse({VA: _gm([0.6], [[10.2, 40.0, 25.0]], [L1])}, far, np.zeros(7), np.eye(7), vehicle=1, unconfirmed=u1)
    u0.born(VA, np.array([L0]))
    fc.fuse({VA: _gm([0.6, 0.9], [[10.0, 40.0, 25.0], [10.55, 40.0, 25.0]], [L1, L0])}, far, np.zeros(7), np.eye(7),
            vehicle=0, unconfirmed=u0)
    g = fc.maps[VA]
    assert g.label[g.mask].tolist() == [L0]  # one landmark, L's label
    assert not fc.confirmation.held[VA] and L0 in fc.confirmation.confirmed[VA]
    for v, u in ((1, u1), (2, u2)):
        down = fc.fuse({VA: nothing}, far, np.zeros(7), np.eye(7), vehicle=v, unconfirmed=u)
        assert down[VA].mask.sum() == 1
