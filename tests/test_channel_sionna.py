"""Rays from Sionna RT (issue 11): LOS Doppler and gain against closed form; CIR/CFR against
Sionna's own ``Paths.cir`` / ``Paths.taps`` / ``Paths.cfr`` on the same traced scene."""
from __future__ import annotations

import numpy as np
import pytest

from mmslam.raytrace.channel import channel_response, subcarrier_frequencies
from mmslam.raytrace.schema import PATH_COLUMNS, RAY_COLUMNS
from mmslam.scenes.scenario import load_preset
from mmslam.scenes.trajectory import vehicle_trajectories
from mmslam.slam.models.measurement import BS

C = 299_792_458.0
STEPS = (0, 11, 25)


@pytest.fixture(scope="module")
def traced(tmp_path_factory):
    from mmslam.raytrace.sionna_adapter import SionnaSource

    scn = load_preset("paper")
    states = vehicle_trajectories(scn)
    src = SionnaSource(scn, max_depth=1, samples_per_src=10**5, seed=0,
                       scene_dir=tmp_path_factory.mktemp("paper_scene_ch"))
    out = {}
    for k in STEPS:
        t = src.trace_tables(k, states[k])
        p = src.last_paths
        f = subcarrier_frequencies(64, 400e6 / 64)
        import mitsuba as mi

        ref = {
            "cfr": np.asarray(p.cfr(frequencies=mi.Float(f), out_type="numpy")),
            "cfr_t": np.asarray(p.cfr(frequencies=mi.Float(f), sampling_frequency=1e3, num_time_steps=3,
                                      out_type="numpy")),
            "taps": np.asarray(p.taps(400e6, l_min=-3, l_max=40, out_type="numpy")),
            "cir": [np.asarray(x) for x in p.cir(out_type="numpy")],
        }
        out[k] = (t, ref)
    return scn, states, out


def test_tables_complete_and_every_valid_path_kept(traced):
    _, _, out = traced
    for k, (t, _) in out.items():
        assert set(t["rays"]) == set(RAY_COLUMNS) and set(t["paths"]) == set(PATH_COLUMNS)
        r = t["rays"]
        n = len(r["rx"])
        assert n >= len(t["paths"]["rx"]) and np.all(r["step"] == k)
        # every path row is a ray of the same receiver with the same label, delay and power
        for i in range(len(t["paths"]["rx"])):
            j = np.flatnonzero((r["rx"] == t["paths"]["rx"][i]) & (r["ray"] == t["paths"]["ray"][i]))
            assert j.size == 1
            assert r["landmark_id"][j[0]] == t["paths"]["landmark_id"][i]
            assert r["delay_s"][j[0]] * C == pytest.approx(t["paths"]["toa_m"][i], rel=1e-12)
        # cluster sizes add up: rays of labelled landmarks = sum of n_paths (own-car rays excluded)
        assert t["paths"]["n_paths"].sum() <= n
        for rx in np.unique(r["rx"]):
            rr = np.sort(r["ray"][r["rx"] == rx])
            np.testing.assert_array_equal(rr, np.arange(rr.size))


def test_los_doppler_is_velocity_projection_and_gain_is_friis(traced):
    scn, states, out = traced
    lam = C / scn.frequency_hz
    b = scn.bs_array
    n = 0
    for k, (t, _) in out.items():
        r = t["rays"]
        for j in np.flatnonzero(r["type"] == BS):
            st = states[k, r["rx"][j]]
            u = st[:3]
            v = st[4] * np.array([np.cos(st[3]), np.sin(st[3]), 0.0])
            d = np.linalg.norm(b - u)
            want = v @ (b - u) / d / lam
            assert abs(r["doppler_hz"][j] - want) <= 1e-3 * max(st[4], 1.0), (k, r["doppler_hz"][j], want)
            friis = 20 * np.log10(lam / (4 * np.pi * d))
            assert abs(r["power_db"][j] - friis) < 0.1
            n += 1
    assert n == 2 * len(out)


def test_vs_doppler_includes_the_other_cars_motion(traced):
    """A VS ray off the other car: Doppler = -(1/lambda) dL/dt with both cars moving."""
    scn, states, out = traced
    lam = C / scn.frequency_hz
    b = scn.bs_array
    unit = lambda x: x / np.linalg.norm(x)  # noqa: E731
    n = 0
    for k, (t, _) in out.items():
        r = t["rays"]
        for j in np.flatnonzero((r["type"] == 3) & (r["bounces"] == 1)):
            rx = r["rx"][j]
            other = 1 - rx
            s = np.array([r["bounce1_x"][j], r["bounce1_y"][j], r["bounce1_z"][j]])
            u = states[k, rx, :3]
            vu = states[k, rx, 4] * np.array([np.cos(states[k, rx, 3]), np.sin(states[k, rx, 3]), 0.0])
            vs = states[k, other, 4] * np.array([np.cos(states[k, other, 3]), np.sin(states[k, other, 3]), 0.0])
            want = (vu @ unit(s - u) - vs @ (unit(s - b) + unit(s - u))) / lam
            assert r["doppler_hz"][j] == pytest.approx(want, abs=1.0), (k, j)  # 1 Hz = 1 cm/s (float32 vertices)
            n += 1
    assert n > 0


def test_cfr_and_taps_equal_sionna(traced):
    """Float32 tolerance: Sionna evaluates the phases 2 pi (f_c + f) tau (up to ~1e4 rad) in float32;
    measured max |difference| / max |H|: CFR ~1e-3, taps ~2e-5."""
    scn, _, out = traced
    fc = scn.frequency_hz
    for k, (t, ref) in out.items():
        r = t["rays"]
        h, f, _, _ = channel_response(r, kind="cfr", carrier_hz=fc, bandwidth_hz=400e6, n_subcarriers=64, n_rx=2)
        want = ref["cfr"].reshape(2, 1, 64)
        scale = np.abs(want).max()
        np.testing.assert_allclose(h[0], want, atol=2e-3 * scale, rtol=0)
        h3, _, _, _ = channel_response(r, kind="cfr", carrier_hz=fc, bandwidth_hz=400e6, n_subcarriers=64, n_rx=2,
                                       num_time_steps=3, sampling_frequency_hz=1e3)
        np.testing.assert_allclose(h3[0], ref["cfr_t"].reshape(2, 3, 64), atol=2e-3 * scale, rtol=0)
        taps, ax, _, _ = channel_response(r, kind="cir", carrier_hz=fc, bandwidth_hz=400e6, n_subcarriers=64,
                                          n_rx=2, l_min=-3, l_max=40)
        assert ax[0] == -3 and ax[-1] == 40
        tscale = np.abs(ref["taps"]).max()
        np.testing.assert_allclose(taps[0], ref["taps"].reshape(2, 1, 44), atol=1e-4 * tscale, rtol=0)
        # the cir's (a, tau) of the valid paths: same multiset of normalised delays per receiver
        _, tau = ref["cir"]
        tau = tau.reshape(2, -1)
        for rx in range(2):
            got = np.sort(r["delay_s"][r["rx"] == rx] - r["delay_s"][r["rx"] == rx].min())
            np.testing.assert_allclose(got, np.sort(tau[rx][tau[rx] >= 0]), atol=1e-12)
