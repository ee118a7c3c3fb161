"""Two path caches of one scenario, traced on different backends (CUDA / LLVM) or machines, compared row by row.

Usage::

    python benchmarks/compare_traces.py CACHE_A CACHE_B

Rows (one per resolvable landmark, receiver and step: the ``paths`` table of docs/dataset.md) are matched by
``(step, rx, type)`` and the landmark position rounded to 0.1 m (a landmark on a rounding boundary would show as one
row only in each cache). Prints the row counts (and how many rows share a key: 0 in a trace, whose rows are one per
landmark, receiver and step), the rows found in one cache only (at most five of each, with their power), and per
column the largest and the median absolute difference of the matched rows, in the column's unit (m, rad wrapped to
[-pi, pi), dB, Hz). Sionna RT computes in float32: on canyon and munich the CUDA and LLVM traces agree in ToA,
angles and Doppler to a few float32 ulps and in power to 1.4e-3 dB (docs/implementation-notes.md, "Tracing on a
CUDA device"). Exit status 0; 2 with a one-line message if a cache cannot be read.
"""
from __future__ import annotations

import argparse
import sys

import numpy as np

COLUMNS = ("toa_m", "aod_az", "aod_el", "aoa_az", "aoa_el", "power_db", "doppler_hz")
ANGLES = ("aod_az", "aod_el", "aoa_az", "aoa_el")


def paths_table(cache: str) -> dict[str, np.ndarray]:
    """The cache's ``paths`` table as column arrays."""
    from mmslam.raytrace.cache import load_cache

    p = load_cache(cache).paths
    return {k: np.asarray(v) for k, v in (p.items() if isinstance(p, dict) else p.to_pydict().items())}


def row_keys(p: dict[str, np.ndarray]) -> list[tuple[int, int, int, float, float, float]]:
    """``(step, rx, type, x, y, z)`` per row, the landmark position rounded to 0.1 m."""
    xyz = np.round(np.stack([p["lm_x"], p["lm_y"], p["lm_z"]], -1).astype(float), 1)
    return [(int(s), int(r), int(t), *map(float, x)) for s, r, t, x in zip(p["step"], p["rx"], p["type"], xyz)]


def compare(a: dict[str, np.ndarray], b: dict[str, np.ndarray]) -> dict[str, object]:
    """Matched rows and per-column ``(max, median)`` absolute differences of two ``paths`` tables."""
    ka, kb = row_keys(a), row_keys(b)
    ia = {k: i for i, k in enumerate(ka)}
    ib = {k: i for i, k in enumerate(kb)}
    common = sorted(set(ia) & set(ib))
    out: dict[str, object] = {"rows": (len(ka), len(kb), len(common)),
                              "shared_keys": (len(ka) - len(ia), len(kb) - len(ib)),
                              "only_a": sorted(set(ia) - set(ib)), "only_b": sorted(set(ib) - set(ia)), "diff": {}}
    if common:
        i = np.array([ia[k] for k in common])
        j = np.array([ib[k] for k in common])
        for col in COLUMNS:
            if col in a and col in b:
                d = a[col][i].astype(float) - b[col][j].astype(float)
                if col in ANGLES:
                    d = (d + np.pi) % (2 * np.pi) - np.pi
                out["diff"][col] = (float(np.abs(d).max()), float(np.median(np.abs(d))))
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("cache_a")
    ap.add_argument("cache_b")
    args = ap.parse_args(argv)
    try:
        a, b = paths_table(args.cache_a), paths_table(args.cache_b)
    except Exception as e:  # a missing or foreign cache: one line, exit 2
        print(f"error: {e}", file=sys.stderr)
        return 2
    r = compare(a, b)
    na, nb, nc = r["rows"]
    sa, sb = r["shared_keys"]
    print(f"rows: A {na}, B {nb}, matched {nc}, only in A {len(r['only_a'])}, only in B {len(r['only_b'])}; "
          f"rows sharing a key: A {sa}, B {sb}")
    for tag, rows, p, idx in (("A", r["only_a"], a, row_keys(a)), ("B", r["only_b"], b, row_keys(b))):
        pos = {k: n for n, k in enumerate(idx)}
        for k in rows[:5]:
            print(f"  only in {tag}: step {k[0]} rx {k[1]} type {k[2]} at {k[3:]}, "
                  f"power {p['power_db'][pos[k]]:.1f} dB")
    for col, (mx, med) in r["diff"].items():
        print(f"  {col:10s} max |A - B| {mx:.3g}, median {med:.3g}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
