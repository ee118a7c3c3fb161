"""The result of one filter run (one variant, one seed) and its on-disk form.

:class:`Result` holds three column tables (dicts of equal-length NumPy arrays) and ``meta``:

``vehicles`` (one row per step and vehicle)
    step int32, vehicle int16, x, y, z [m], heading [rad], bias [m] (posterior-mean estimates),
    true_x, true_y, true_z [m], true_heading [rad], true_bias [m], pos_err [m] (3-D),
    pos_nees (the horizontal position's NEES against the weighted particle covariance, 2 degrees of freedom:
    mean 2 when the filter's spread matches its error; NaN where that covariance is singular),
    heading_err [rad] (wrapped), bias_err [m]

``metrics`` (one row per step, map and landmark type)
    step int32, map string (a vehicle name for its local averaged map, or "fused" for the BS
    map), type string (a mapped landmark type of :mod:`mmslam.slam.specs.landmarks`: "VA" | "SP" | "VS"
    built in, whether or not the variant maps it), gospa, loc, missed, false [m] (GOSPA p=2, c, alpha=2,
    with its localisation / missed / false parts; gospa**2 = loc + missed + false),
    n_est int32, n_true int32, card (the PHD mass: sum of the map's weights, the expected
    number of landmarks of that type), n_visible int32 (landmarks of that type the map's vehicle,
    or any vehicle for "fused", could detect at that step: in its paths and inside its FOV;
    n_true counts every landmark from its first sighting on)

``landmarks`` (estimated landmarks, one row per step, map, type and estimate)
    step int32, map string, type string, x, y, z [m], weight float64

``meta``: variant, particles, seed, scenario, cache (config hash), source, steps, vehicle_names,
wall_time_s, mmslam version.

Saved as ``vehicles.parquet``, ``metrics.parquet``, ``landmarks.parquet`` and ``meta.json`` in
one directory, with the output marker of :mod:`mmslam.outputs` (kind ``"result"``), written to a
temporary sibling and renamed (atomic). An existing target is replaced only if it is empty or a
previous result (or with ``force``); a user's folder is never deleted.
"""
from __future__ import annotations

import json
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from mmslam.errors import CacheError
from mmslam.outputs import check_target, make_temp_dir, replace_dir, write_marker

TABLES = ("vehicles", "metrics", "landmarks")
RESULT_KIND = "result"
RESULT_FILES = frozenset({*(f"{t}.parquet" for t in TABLES), "meta.json"})
"""Everything a result directory holds besides its marker: only these are ever deleted when it is replaced."""


@dataclass
class Result:
    vehicles: dict[str, np.ndarray]
    metrics: dict[str, np.ndarray]
    landmarks: dict[str, np.ndarray]
    meta: dict[str, Any] = field(default_factory=dict)

    def save(self, out_dir: str | Path, force: bool = False) -> Path:
        """Write atomically to ``out_dir``. Returns the path.

        An existing ``out_dir`` is replaced only when it is empty or a previous result holding
        nothing but a result's files (:data:`RESULT_FILES`), each as mmslam wrote it (the marker's
        digests); anything else (a user's folder, a file the user added to a result or edited there)
        raises a one-line :class:`~mmslam.errors.MmslamError`, whatever ``force`` (kept for callers;
        :mod:`mmslam.outputs`). A symbolic link is followed and kept.
        """
        import pyarrow as pa
        import pyarrow.parquet as pq

        out = Path(out_dir)
        out.parent.mkdir(parents=True, exist_ok=True)
        out = check_target(out, RESULT_KIND, force, own_names=RESULT_FILES, writes=RESULT_FILES)
        tmp = make_temp_dir(out.parent, out.name)
        try:
            for name in TABLES:
                cols = getattr(self, name)
                table = pa.table({k: pa.array(np.asarray(v).tolist() if np.asarray(v).dtype == object
                                              else np.asarray(v)) for k, v in cols.items()})
                pq.write_table(table, tmp / f"{name}.parquet")
            (tmp / "meta.json").write_text(json.dumps(self.meta, indent=2, default=_jsonable))
            write_marker(tmp, RESULT_KIND, files=RESULT_FILES)
            replace_dir(tmp, out, RESULT_KIND, force, own_names=RESULT_FILES, writes=RESULT_FILES)
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        return out

    @classmethod
    def load(cls, path: str | Path) -> "Result":
        """Read a result directory written by :meth:`save`."""
        import pyarrow.parquet as pq

        p = Path(path)
        if not (p / "meta.json").is_file():
            raise CacheError(f"{p}: not a result directory (no meta.json); run 'mmslam slam' to create it")
        try:
            meta = json.loads((p / "meta.json").read_text())
            tabs = {}
            for name in TABLES:
                t = pq.read_table(p / f"{name}.parquet")
                tabs[name] = {c: t.column(c).to_numpy(zero_copy_only=False) for c in t.column_names}
        except Exception as e:  # corrupt / truncated files
            raise CacheError(f"{p}: unreadable result ({type(e).__name__}: {e}); delete it and re-run") from None
        return cls(tabs["vehicles"], tabs["metrics"], tabs["landmarks"], meta)


def _jsonable(o: Any) -> Any:
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(f"not JSON-serialisable: {type(o).__name__}")
