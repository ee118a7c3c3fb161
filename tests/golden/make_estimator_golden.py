"""Golden fixture of the channel-parameter estimator: :func:`nomp`'s output on clustered channels.

``tests/golden/estimator_nomp.npz`` holds, for each seed of :data:`SEEDS`, the frequencies ``w (L, 5)``
and complex amplitudes ``g (L,)`` that :func:`mmslam.slam.sim.channel_estimator.nomp` returned on
:func:`clustered_channel` (default grid, pfa 0.01, at most 20 paths), written by the code as of commit
1b6f414 (the numpy estimator before the compiled one). Each channel has four clusters (a 50 dB LOS-like
path and three weaker ones, each with 2-5 diffuse rays within 1.5 DFT cells of it, 8-22 dB weaker):
the case where the cyclic refinement moves earlier paths (5-14 moves per channel with that code).

``tests/test_channel_estimator.py::test_estimates_equal_the_golden_fixture`` compares. Regenerate only when
a change is meant to change the estimates (say so in the commit message)::

    .venv/bin/python tests/golden/make_estimator_golden.py
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from mmslam.slam.sim import channel_estimator as ce

GRID = ce.Grid(tx_array=8, rx_array=4, n_subcarriers=256, bandwidth_hz=400e6)  # the defaults
SEEDS = (1, 2, 4)
PATH = Path(__file__).with_name("estimator_nomp.npz")


def clustered_channel(seed: int, grid: ce.Grid = GRID) -> np.ndarray:
    """Unit-noise pilots ``(rx, rx, tx, tx, K)`` of four clusters of paths (module docstring), seeded."""
    rng = np.random.default_rng(seed)
    cell = 2 * np.pi / np.array(grid.shape)
    centres = rng.uniform(-np.pi, np.pi, (4, 5))
    snr_c = np.array([50.0, 38.0, 32.0, 26.0])  # integrated SNR (dB) of each cluster's main path
    Y = (rng.standard_normal(grid.shape) + 1j * rng.standard_normal(grid.shape)) / math.sqrt(2.0)
    for c, s in zip(centres, snr_c):
        for r in range(1 + int(rng.integers(2, 6))):
            w = c + (rng.uniform(-1.5, 1.5, 5) * cell if r else 0.0)
            snr = s - (rng.uniform(8, 22) if r else 0.0)
            Y += 10 ** (snr / 20) / math.sqrt(grid.size) * np.exp(2j * np.pi * rng.random()) * ce.atom_tensor(w, grid)
    return Y


def main() -> None:
    out = {}
    for s in SEEDS:
        w, g = ce.nomp(clustered_channel(s), GRID, pfa=0.01)
        out[f"w/{s}"], out[f"g/{s}"] = w, g
        print(f"seed {s}: {len(w)} estimates")
    np.savez(PATH, **out)


if __name__ == "__main__":
    main()
