"""Benchmark: the CKF update kernel (:func:`mmslam.slam.phd.ckf.ckf_update`) per Gaussian.

Captures the real inputs of the CKF updates (Gaussians, particle states, measurements, ``R``)
from steps ``--first..--steps - 1`` of vehicle 1 of a run (``--variant``, default baseline) on the
analytic ``paper`` data (P = 300), then times the compiled batch kernel of each path geometry
on them, on one core, and reports ns per Gaussian (median of ``--repeats`` runs over the
captured batches; mirror = VA, scatter = SP and VS; ``vs`` = the VS batches alone).

    python benchmarks/bench_ckf.py                 # capture steps 5..19, 15 repeats
    python benchmarks/bench_ckf.py --variant proposed   # also VS Gaussians (d = 7, a car-body extent)
    python benchmarks/bench_ckf.py --save X.npz    # keep the captured batches
    python benchmarks/bench_ckf.py --load X.npz    # time saved batches (same inputs across versions)
"""
from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_v] = "1"

import argparse  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402


def capture(steps: int, particles: int = 300, variant: str = "baseline", first: int = 5) -> list[dict]:
    """The CKF batches (every Gaussian with a CKF update: ``m, P``, its particle's state, ``Z``, ``R``,
    extent, geometry) of the correction kernels of :mod:`mmslam.slam.phd.gmphd` in vehicle 1's steps
    ``first..steps-1``."""
    from bench_filter import paper_data

    import mmslam.slam.phd.gmphd as gmphd
    from mmslam.slam.filter.run import CooperativeRun

    scn, states, paths = paper_data(steps)
    run = CooperativeRun(scn, states, paths, variant, particles, 0, steps, evaluate=False)
    calls: list[dict] = []
    orig = gmphd._TYPE_TERMS
    record = [False]

    def spy(geometry: int):  # noqa: ANN202
        def kernel(w, pd, m, P, st, b, extent, body, Z, R, det_index, *rest):  # noqa: ANN001, ANN202
            code = orig[geometry](w, pd, m, P, st, b, extent, body, Z, R, det_index, *rest)
            p, q = np.nonzero(det_index >= 0)  # numbered in this order
            if record[0] and p.size:
                calls.append(dict(m=m[p, q], P=P[p, q], states=st[p], geometry=geometry, bs=np.array(b),
                                  Z=np.array(Z), R=np.array(R), extent=np.array(extent), body=np.array(body)))
            return code
        return kernel

    gmphd._TYPE_TERMS = tuple(spy(g) for g in range(len(orig)))
    try:
        for k in range(steps):
            run.predict_at_bs(k)
            for n in range(run.n_veh):
                Z, spd, tr, R_z = run.local_inputs(k, n)
                record[0] = n == 0 and k >= first
                est = run.filters[n].step(Z, spd, tr, R_z)
                run.upload(k, n, est)
    finally:
        gmphd._TYPE_TERMS = orig
    return calls


def time_batches(calls: list[dict], repeats: int) -> dict[str, tuple[float, int]]:
    """Median ns per Gaussian of the compiled batch kernel, per geometry name, and the Gaussian count."""
    from mmslam.slam.phd.ckf import _CKF_BATCH, MEAS_DIM, workspace

    groups = {"direct": lambda c: c["geometry"] == 0, "mirror": lambda c: c["geometry"] == 1,
              "scatter": lambda c: c["geometry"] == 2, "vs": lambda c: c["m"].shape[1] == 7}
    out = {}
    for name, pick in groups.items():
        sel = [c for c in calls if pick(c)]
        if not sel:
            continue
        args = []
        for c in sel:
            n, d = c["m"].shape
            J = c["Z"].shape[0]
            R = c["R"].reshape(-1, MEAS_DIM, MEAS_DIM)
            args.append((np.ascontiguousarray(c["m"]), np.ascontiguousarray(c["P"]), np.ascontiguousarray(c["states"]),
                         c["bs"], c["extent"], c["body"], np.ascontiguousarray(c["Z"]), np.ascontiguousarray(R),
                         np.empty((n, J)), np.empty((n, J, d)), np.empty((n, R.shape[0], d, d)), workspace(d)))
        kernel = _CKF_BATCH[sel[0]["geometry"]]
        for a in args[:1]:
            kernel(*a)  # compile / load
        total = sum(a[0].shape[0] for a in args)
        times = []
        for _ in range(repeats):
            t0 = time.thread_time_ns()
            for a in args:
                kernel(*a)
            times.append((time.thread_time_ns() - t0) / total)
        out[name] = (float(np.median(times)), total)
    return out


SAVE_KIND = "bench_ckf_batches"
"""The kind tag of a ``--save`` file (:func:`mmslam.outputs.npz_bytes`): only such a file is replaced by a later ``--save``."""


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=20)
    ap.add_argument("--first", type=int, default=5, help="first captured step (as bench_filter's --warmup)")
    ap.add_argument("--variant", default="baseline", help="filter variant of the captured run")
    ap.add_argument("--repeats", type=int, default=15)
    ap.add_argument("--save", help="save the captured batches (npz)")
    ap.add_argument("--load", help="time batches saved by --save instead of capturing")
    a = ap.parse_args()
    if a.save:  # before the capture: a refused --save loses nothing; a user's file is never replaced
        from mmslam.outputs import check_npz_target

        check_npz_target(a.save, SAVE_KIND, option="--save")
    if a.load:
        from mmslam.errors import MmslamError

        try:
            with np.load(a.load) as f:
                k = int(f["count"])
                calls = [{key: (int(f[f"{i}_{key}"]) if key == "geometry" else f[f"{i}_{key}"])
                          for key in ("m", "P", "states", "geometry", "bs", "Z", "R", "extent", "body")}
                         for i in range(k)]
        except (OSError, ValueError, KeyError) as e:
            raise MmslamError(f"--load {a.load}: not a batch file of this bench_ckf.py ({e}); capture and --save "
                              "it again") from None
    else:
        calls = capture(a.steps, variant=a.variant, first=a.first)
    if a.save:
        from mmslam.outputs import atomic_write_bytes, npz_bytes

        flat = {f"{i}_{key}": v for i, c in enumerate(calls) for key, v in c.items()}
        atomic_write_bytes(a.save, npz_bytes(SAVE_KIND, count=len(calls), **flat), fsync=False)
    for name, (ns, total) in time_batches(calls, a.repeats).items():
        print(f"{name:8s} {total:7d} Gaussians  {ns:7.1f} ns/Gaussian (median of {a.repeats}, thread CPU time)")
    return 0


if __name__ == "__main__":
    from script_entry import run

    run(main, "bench_ckf.py")
