"""CFR with the BS and vehicle arrays (issue 24): equal to Sionna RT's own ``Paths.cfr`` with the same
``PlanarArray`` elements (horizontal mounts, vehicle yaw = heading) on ``paper`` and ``munich``;
array geometry against hand-computed values."""
from __future__ import annotations

import math

import numpy as np
import pytest

from mmslam import arrays
from mmslam.raytrace.channel import channel_response, subcarrier_frequencies
from mmslam.scenes.scenario import load_preset
from mmslam.scenes.trajectory import vehicle_trajectories

NT, NR, K = 4, 3, 32  # small arrays keep Sionna's (rx, rx_ant, tx, tx_ant, paths) tensors small


def test_element_order_and_mounts_by_hand():
    y, z = arrays.element_grid(2)
    # Sionna PlanarArray(2, 2): column-first from the top-left: (y, z) = (-.25, .25), (-.25, -.25), (.25, .25), ...
    np.testing.assert_allclose(y, [-0.25, -0.25, 0.25, 0.25])
    np.testing.assert_allclose(z, [0.25, -0.25, 0.25, -0.25])
    # vehicle mount, heading 90 deg: local z (top row) -> backwards = -y global, local y -> -x global (left of +y)
    p = arrays.element_positions(2, yaw=math.pi / 2, pitch=arrays.VEHICLE_PITCH)
    np.testing.assert_allclose(p[0], [0.25, -0.25, 0.0], atol=1e-15)
    # a wave from straight above: every element in phase; from the heading direction at the horizon:
    # phase 2 pi x (position along it)
    up = arrays.direction_to_local(0.3, math.pi / 2, 1.0, arrays.VEHICLE_PITCH)
    np.testing.assert_allclose(arrays.response(2, up), np.ones(4), atol=1e-12)
    fwd = arrays.direction_to_local(math.pi / 2, 0.0, math.pi / 2, arrays.VEHICLE_PITCH)
    np.testing.assert_allclose(arrays.response(2, fwd), np.exp(2j * np.pi * p[:, 1]), atol=1e-12)
    # round trip: directions in the half-space each array faces
    az, el = np.array([0.1, 2.5, -2.9]), np.array([0.2, 1.1, 0.05])
    for pitch, sgn, yaw in ((arrays.VEHICLE_PITCH, 1.0, 0.7), (arrays.BS_PITCH, -1.0, 0.0)):
        a2, e2 = arrays.local_to_direction(arrays.direction_to_local(az, sgn * el, yaw, pitch), pitch)
        np.testing.assert_allclose(np.angle(np.exp(1j * (a2 + yaw - az))), 0.0, atol=1e-9)
        np.testing.assert_allclose(e2, sgn * el, atol=1e-9)


def _sionna_arrays(rt, mi, n: int, pitch: float):
    """A Sionna ``PlanarArray(n, n)`` (iso, V) whose positions are rotated by the mount's pitch."""
    a = rt.PlanarArray(num_rows=n, num_cols=n, pattern="iso", polarization="V")
    p = arrays.element_positions(n, 0.0, pitch)  # wavelengths
    a.normalized_positions = mi.Point3f(*(mi.Float(p[:, i].astype(np.float32)) for i in range(3)))
    return a


def _compare(name: str, steps: tuple[int, ...], tmp_path, samples: int) -> float:
    import mitsuba as mi

    from mmslam.raytrace.sionna_adapter import SionnaSource, _rx_name

    scn = load_preset(name)
    states = vehicle_trajectories(scn)
    src = SionnaSource(scn, max_depth=1, samples_per_src=samples, seed=0, scene_dir=tmp_path)
    rt = src._rt
    single = (src.scene.tx_array, src.scene.rx_array)
    tx_arr, rx_arr = _sionna_arrays(rt, mi, NT, arrays.BS_PITCH), _sionna_arrays(rt, mi, NR, arrays.VEHICLE_PITCH)
    f = subcarrier_frequencies(K, 400e6 / K)
    worst, n_links = 0.0, 0
    n_rx = len(scn.vehicles)
    for k in steps:
        for v in scn.vehicles:  # yaw only: an iso / V element is invariant, so the traced gains stay valid
            src.scene.receivers[_rx_name(v.name)].orientation = mi.Point3f(float(states[k, scn.vehicle_names.index(v.name), 3]), 0.0, 0.0)
        # the rays table from single antennas (the adapter's setting: ``a`` at the array centre), then
        # the same step again (deterministic solver, same seed) with the arrays for Sionna's CFR
        src.scene.tx_array, src.scene.rx_array = single
        t = src.trace_tables(k, states[k])
        src.scene.tx_array, src.scene.rx_array = tx_arr, rx_arr
        src.raw_paths(k, states[k])
        ref = np.asarray(src.last_paths.cfr(frequencies=mi.Float(f), out_type="numpy"))  # (rx, rx_ant, tx, tx_ant, T, K)
        ref = ref[:, :, 0]  # one transmitter
        h, _, _, _ = channel_response(t["rays"], kind="cfr", carrier_hz=scn.frequency_hz, bandwidth_hz=400e6,
                                      n_subcarriers=K, n_rx=n_rx, steps=np.array([k]), tx_array=NT, rx_array=NR,
                                      rx_heading=states[k:k + 1, :, 3])
        assert h.shape == (1, n_rx, NR * NR, NT * NT, 1, K)
        assert ref.shape == h.shape[1:]
        for rx in range(n_rx):  # relative error per link (links differ in power by orders of magnitude)
            scale = np.abs(ref[rx]).max()
            if scale == 0:  # a receiver without paths (munich: blocked): no channel on either side
                assert not np.any(h[0, rx])
                continue
            n_links += 1
            err = np.abs(h[0, rx] - ref[rx]).max() / scale
            worst = max(worst, err)
            assert err <= 1e-3, (name, k, rx, err)
            # the arrays matter: two receive elements see different channels
            assert np.abs(h[0, rx, 1] - h[0, rx, 0]).max() > 0.05 * np.abs(h[0, rx]).max()
    assert n_links >= len(steps)
    return worst


def test_array_cfr_equals_sionna_on_paper(tmp_path):
    _compare("paper", (0, 25), tmp_path, 10**5)


@pytest.mark.slow
def test_array_cfr_equals_sionna_on_munich(tmp_path):
    _compare("munich", (0,), tmp_path, 10**5)


def test_export_cfr_with_arrays_hand_computed(tmp_path, capsys):
    """Two rays at the same height as the BS (LOS from -x, the wall's image from +x), vehicle heading pi:
    element (m, n)'s CFR = sum_i a_i^b exp(j 2 pi (p_m . k_rx,i + q_n . k_tx,i)) exp(-j 2 pi f tau_i)
    with the element positions written out by hand."""
    import json

    from mmslam.cli import main
    from mmslam.raytrace.analytic import AnalyticSource
    from mmslam.raytrace.cache import load_cache
    from mmslam.raytrace.trace import trace_scenario
    from mmslam.scenes.scenario import scenario_from_dict

    scn = scenario_from_dict({
        "name": "tworay", "bs": [0.0, 0.0, 10.0], "dt": 0.25, "steps": 2,
        "buildings": [{"name": "w", "min": [20.0, -5.0, 0.0], "max": [25.0, 5.0, 20.0]}],
        "vehicles": [{"name": "car0", "initial_state": [5.0, 0.0, 10.0, np.pi, 10.0, 0.0, 0.0]}],
        "sensor": {"fov_range": 1.0, "tx_array": 2, "rx_array": 3},
    })
    d = trace_scenario(scn, AnalyticSource(scn), tmp_path / "c", progress=False)
    r = load_cache(d).read_rays()
    s0 = r["step"] == 0
    a = (r["a_re"] + 1j * r["a_im"])[s0]
    tau = r["delay_s"][s0] - r["delay_s"][s0].min()
    fc, W, N = scn.frequency_hz, 100e6, 8
    f = (np.arange(N) - N // 2) * W / N
    # BS (normal down, yaw 0): local (0, y, z) -> (z, y, 0); departures along +x (LOS) and +x (to the wall)
    yt, zt = np.array([-.25, -.25, .25, .25]), np.array([.25, -.25, .25, -.25])
    qt = np.stack([zt, yt, 0 * yt], 1)
    # vehicle (normal up) at heading pi: local (0, y, z) -> R_z(pi) (-z, y, 0) = (z, -y, 0)
    g = (np.arange(9) // 3 - 1) * 0.5, (1 - np.arange(9) % 3) * 0.5
    pr = np.stack([g[1], -g[0], 0 * g[0]], 1)
    kt = np.array([[1.0, 0, 0], [1.0, 0, 0]])  # BS -> car (+x), BS -> wall (+x)
    kr = np.array([[-1.0, 0, 0], [1.0, 0, 0]])  # the car sees the BS at -x, the wall's image at +x
    order = np.argsort(r["delay_s"][s0])  # LOS first
    a, tau = a[order], tau[order]
    want = np.einsum("im,in,ik->mnk", np.exp(2j * np.pi * kr @ pr.T), np.exp(2j * np.pi * kt @ qt.T),
                     a[:, None] * np.exp(-2j * np.pi * (fc + f)[None, :] * tau[:, None]))
    out = tmp_path / "h.npz"
    assert main(["export", str(d), "--cfr", "--arrays", "--bandwidth", str(W), "--subcarriers", str(N),
                 "--out", str(out)]) == 0
    z = np.load(out)
    assert z["h"].shape == (2, 1, 9, 4, 1, N)
    np.testing.assert_allclose(z["h"][0, 0, :, :, 0], want, rtol=0, atol=1e-5 * np.abs(want).max())
    meta = json.loads(str(z["meta"]))
    assert meta["tx_array"] == 2 and meta["rx_array"] == 3 and "rx_ant, tx_ant" in meta["h"]
    assert "rx_ant, tx_ant" in capsys.readouterr().out
