"""Path-cache schema (DESIGN.md section 7) and the path-source protocol.

Two tables, both keyed by ``step`` (0-based time index; time ``t = step * dt`` s):

``vehicles`` (one row per step and vehicle; true states, global frame)
    step int32, t float64 [s], vehicle int16 (index into manifest ``vehicle_names``),
    x, y, z float64 [m] (antenna position), heading float64 [rad], speed float64 [m/s],
    turn_rate float64 [rad/s]

``paths`` (one row per step, receiving vehicle and resolvable landmark; noise-free)
    step int32, rx int16 (receiving vehicle index), type int8 (0 BS, 1 VA, 2 SP, 3 VS, 4 OTHER),
    landmark_id string (BS: "bs"; VA: "<object>:<face>" e.g. "wall_east:-x"; SP: scatterer name;
    VS: vehicle name; OTHER: "+"-joined object names of the bounces),
    bounces int8 (0 for LOS), diffuse bool (any diffuse bounce),
    toa_m float64 [m] (delay x c, no clock bias), aod_az, aod_el, aoa_az, aoa_el float64 [rad]
    (global frame; AOA azimuth NOT heading-corrected), power_db float64 [dB] (NaN if unknown),
    bounce_x, bounce_y, bounce_z float64 [m] (first interaction point; NaN for LOS),
    lm_x, lm_y, lm_z float64 [m] (ground-truth landmark: BS position, VA image source,
    SP reference point, VS antenna position of that vehicle at this step; NaN for OTHER),
    n_paths int32 (traced paths merged into this row: a diffuse cluster), delay_spread_m float64
    [m] (max - min TOA in the cluster; 0 for a single path)

Rows are sorted by (step, rx, type, landmark_id): deterministic whatever the solver's path order.
"""
from __future__ import annotations

from typing import Protocol

import numpy as np

SCHEMA_VERSION = 1

VEHICLE_COLUMNS: dict[str, str] = {
    "step": "int32", "t": "float64", "vehicle": "int16", "x": "float64", "y": "float64",
    "z": "float64", "heading": "float64", "speed": "float64", "turn_rate": "float64",
}

PATH_COLUMNS: dict[str, str] = {
    "step": "int32", "rx": "int16", "type": "int8", "landmark_id": "string", "bounces": "int8",
    "diffuse": "bool", "toa_m": "float64", "aod_az": "float64", "aod_el": "float64",
    "aoa_az": "float64", "aoa_el": "float64", "power_db": "float64",
    "bounce_x": "float64", "bounce_y": "float64", "bounce_z": "float64",
    "lm_x": "float64", "lm_y": "float64", "lm_z": "float64",
    "n_paths": "int32", "delay_spread_m": "float64",
}


class PathSource(Protocol):
    """Something that turns true vehicle states at one step into labelled paths.

    Implementations: :class:`mmslam.raytrace.analytic.AnalyticSource` (closed form, no Sionna)
    and :class:`mmslam.raytrace.sionna_adapter.SionnaSource` (Sionna RT PathSolver).
    """

    name: str  # "analytic" | "sionna"

    def settings(self) -> dict:
        """Solver settings that change the result (part of the cache's config hash)."""
        ...

    def versions(self) -> dict[str, str]:
        """Library versions recorded in the manifest (e.g. sionna-rt, mitsuba, drjit)."""
        ...

    def trace_step(self, step: int, states: np.ndarray) -> dict[str, np.ndarray]:
        """Paths for all receivers at one step.

        Args:
            step: time index.
            states: ``(n_vehicles, 7)`` true vehicle states ``[x, y, z, heading, speed,
                turn_rate, bias]`` at this step (global frame).

        Returns:
            Columns of the ``paths`` table (all of :data:`PATH_COLUMNS`), equal-length NumPy
            arrays (``landmark_id`` an object/str array), sorted by (rx, type, landmark_id).
        """
        ...


def empty_paths() -> dict[str, np.ndarray]:
    """A zero-row ``paths`` column dict with the schema's dtypes."""
    out: dict[str, np.ndarray] = {}
    for k, t in PATH_COLUMNS.items():
        out[k] = np.empty(0, dtype=object if t == "string" else np.dtype(t))
    return out


def sort_paths(cols: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Sort path columns by (step, rx, type, landmark_id), stably."""
    n = len(cols["rx"])
    if n == 0:
        return cols
    step = cols.get("step", np.zeros(n, np.int32))
    ids = np.asarray(cols["landmark_id"]).astype(str)
    order = np.lexsort((ids, cols["type"], cols["rx"], step))
    return {k: np.asarray(v)[order] for k, v in cols.items()}
