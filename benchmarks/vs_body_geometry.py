"""How well the car-body VS model places the bounce of the traced VS paths (issue 22, docs/city-slam.md).

Usage::

    python benchmarks/vs_body_geometry.py CACHE_DIR [CACHE_DIR ...]

For every VS row of each cache (a path BS -> another car's body -> receiver, traced on car meshes), the path
length predicted through a point is compared with the traced one (``toa_m``), for: the car's antenna (the point
VS of the paper), the specular point of the car body (:func:`mmslam.slam.models.vs.body_specular_point`, the
scenario's car size, centre ``roof_gap + height / 2`` below the antenna) with the true heading, with the heading
off by N(0, 0.3^2) rad, and with a uniformly random heading (the birth's case). Prints mean and rms error (m).
Also prints the bounce heights relative to the receiving antenna of VS and VA paths within ``sensor.fov_range``
(the band of ``filter.vs_birth_height``) and which share of each lies within 2, 3, 4 and 5 m.
"""
from __future__ import annotations

import argparse
import sys

import numpy as np


def main(argv: list[str] | None = None) -> int:
    from mmslam.model import VA, VS
    from mmslam.raytrace.cache import load_cache
    from mmslam.slam.models.vs import body_points

    ap = argparse.ArgumentParser()
    ap.add_argument("cache", nargs="+")
    a = ap.parse_args(argv)
    rng = np.random.default_rng(0)
    for cache in a.cache:
        c = load_cache(cache)
        p, scn = c.paths, c.scenario
        names = list(scn.vehicle_names)
        ty, st, rx = np.asarray(p["type"]), np.asarray(p["step"]), np.asarray(p["rx"])
        b = np.array([p["tx_x"][0], p["tx_y"][0], p["tx_z"][0]], float)
        sel = np.nonzero(ty == VS)[0]
        print(f"== {scn.name} ({cache}): {sel.size} VS rows")
        if sel.size:
            tgt = np.array([names.index(str(i)) for i in np.asarray(p["landmark_id"])[sel]])
            k, r = st[sel], rx[sel]
            x, u, hd = c.states[k, tgt, 0:3], c.states[k, r, 0:3], c.states[k, tgt, 3]
            cars = [scn.vehicles[i] for i in tgt]
            length = np.asarray(p["toa_m"], float)[sel]
            arms = {"antenna point": x}
            for name, h in (("body, true heading", hd), ("body, heading +- 0.3 rad", hd + rng.normal(0, 0.3, hd.size)),
                            ("body, heading unknown", rng.uniform(-np.pi, np.pi, hd.size))):
                arms[name] = np.concatenate([body_points(x[i:i + 1], h[i:i + 1], b, u[i:i + 1],
                                                         np.array([v.length, v.width, v.height, v.roof_gap + v.height / 2]))
                                             for i, v in enumerate(cars)])
            for name, q in arms.items():
                e = np.linalg.norm(b - q, axis=1) + np.linalg.norm(q - u, axis=1) - length
                print(f"  {name:26s} path length error: mean {e.mean():+.2f} m, rms {np.sqrt(np.mean(e ** 2)):.2f} m")
        hit = np.stack([np.asarray(p[f"bounce_{ax}"], float) for ax in "xyz"], -1)
        dz = hit[:, 2] - c.states[st, rx, 2]
        near = np.linalg.norm(hit - c.states[st, rx, 0:3], axis=1) <= scn.sensor.fov_range
        for code, name in ((VS, "VS"), (VA, "VA")):
            s = (ty == code) & near
            if s.any():
                share = "  ".join(f"<= {t} m: {np.mean(np.abs(dz[s]) <= t):.3f}" for t in (2, 3, 4, 5))
                print(f"  {name} bounce height above the receiver (within {scn.sensor.fov_range:g} m, {s.sum()} rows): "
                      f"5/50/95% {np.percentile(dz[s], [5, 50, 95]).round(1).tolist()} m; |dz| {share}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
