"""Path-cache schema (docs/design.md section 7) and the path-source protocol.

Three tables, all keyed by ``step`` (0-based time index; time ``t = step * dt`` s). Global frame:
x east, y north, z up, metres; angles in radians, azimuth from +x towards +y, elevation above the
xy plane. On disk every table is a directory of Parquet files (``CACHE/<table>/part-NNNNN.parquet``)
readable in one call (``pandas.read_parquet("CACHE/rays")``, ``duckdb "CACHE/rays/*.parquet"``);
enum columns are Arrow dictionaries holding their labels, every field carries ``unit`` and
``doc`` metadata, and the file metadata (key ``mmslam``) holds the scenario and solver settings
(:mod:`mmslam.raytrace.cache`). In memory (:class:`~mmslam.raytrace.cache.PathCache`) enum columns
are integer codes: the index into their labels (:data:`TYPE_LABELS`, :data:`INTERACTION_LABELS`,
the manifest's ``vehicle_names``, :data:`TX_LABELS`).

The columns, their in-memory dtypes, units and meaning are :data:`VEHICLE_SPEC`,
:data:`RAY_SPEC` and :data:`PATH_SPEC` (also rendered in ``docs/dataset.md``):

``vehicles``: one row per step and vehicle (true states).
``rays``: every traced path (no clustering) with its transmitter position, complex gain, delay,
    angles, Doppler shift, interactions and vertices, and its label. ``ray`` numbers the rays of
    one (step, rx) in order of increasing delay.
``paths``: one row per step, receiver and resolvable landmark (what the sensor model reads):
    the strongest ray of each (rx, type, landmark_id) cluster, with ``ray`` linking it to ``rays``
    (join on ``step, rx, ray``; all rays of the cluster share ``step, rx, type, landmark_id``).

Schema versions (:data:`SCHEMA_VERSION`, the manifest's ``schema_version``): 2 introduced the
three self-describing tables; 3 added the transmitter (BS) position ``tx_x, tx_y, tx_z`` to
``rays`` and ``paths`` (:data:`ADDED_COLUMNS`). The loader reads versions
:data:`READABLE_SCHEMA_VERSIONS` and fills the columns a cache's version lacks
(:func:`table_columns`).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from mmslam.model import LandmarkType

SCHEMA_VERSION = 3
"""Schema version this mmslam writes (the manifest's and every file's ``schema_version``)."""

TYPE_LABELS: tuple[str, ...] = tuple(t.name for t in LandmarkType)
"""Landmark type labels; code = index (:class:`mmslam.model.LandmarkType`, BS=0 .. OTHER=4)."""

INTERACTION_LABELS: tuple[str, ...] = ("none", "specular", "diffuse", "refraction", "diffraction")
"""Interaction type labels; code = index. Sionna's InteractionType bits 0/1/2/4/8 map to 0..4."""

TX_LABELS: tuple[str, ...] = ("bs",)
"""Transmitter labels (one BS)."""

MAX_BOUNCES = 3
"""Interaction slots per ray in the ``rays`` table (``bounceK_*`` for K = 1..3)."""

SIONNA_INTERACTION_CODE = {0: 0, 1: 1, 2: 2, 4: 3, 8: 4}
"""Sionna ``InteractionType`` bit value -> :data:`INTERACTION_LABELS` code."""


@dataclass(frozen=True)
class Col:
    """One column: in-memory dtype (``string`` = object array of str), unit, doc, enum labels key.

    ``enum`` is ``"type"``, ``"interaction"``, ``"tx"`` or ``"vehicle"`` (labels: the manifest's
    ``vehicle_names``) for dictionary-encoded columns, else ``None``.
    """

    dtype: str
    unit: str
    doc: str
    enum: str | None = None


TX_POSITION_COLUMNS: tuple[str, str, str] = ("tx_x", "tx_y", "tx_z")
"""The transmitter position columns of ``rays`` and ``paths`` (schema version 3)."""

_TX_POS = {c: Col("float64", "m", f"transmitter (BS antenna) position {c[-1]} (global frame): the scenario's bs, "
                  "the same on every row (one static BS)") for c in TX_POSITION_COLUMNS}

_ANG = {
    "aod_az": "azimuth of departure at the BS (global frame)",
    "aod_el": "elevation of departure at the BS",
    "aoa_az": "azimuth of arrival at the receiver (global frame, NOT heading-corrected)",
    "aoa_el": "elevation of arrival at the receiver",
}

VEHICLE_SPEC: dict[str, Col] = {
    "step": Col("int32", "", "time index"),
    "t": Col("float64", "s", "time step * dt"),
    "vehicle": Col("int16", "", "vehicle name", "vehicle"),
    "x": Col("float64", "m", "antenna position x (global frame)"),
    "y": Col("float64", "m", "antenna position y"),
    "z": Col("float64", "m", "antenna position z"),
    "heading": Col("float64", "rad", "heading, from +x towards +y"),
    "speed": Col("float64", "m/s", "speed"),
    "turn_rate": Col("float64", "rad/s", "turn rate"),
    "vx": Col("float64", "m/s", "velocity x = speed cos(heading)"),
    "vy": Col("float64", "m/s", "velocity y = speed sin(heading)"),
    "vz": Col("float64", "m/s", "velocity z (0)"),
}


def _bounce_cols() -> dict[str, Col]:
    out: dict[str, Col] = {}
    for k in range(1, MAX_BOUNCES + 1):
        out[f"bounce{k}_type"] = Col("int8", "", f"interaction type of bounce {k} ('none': fewer bounces)",
                                     "interaction")
        out[f"bounce{k}_object"] = Col("string", "", f"scene object hit at bounce {k} ('' if none)")
        for a in "xyz":
            out[f"bounce{k}_{a}"] = Col("float64", "m", f"interaction point {a} of bounce {k} (NaN if none)")
    return out


RAY_SPEC: dict[str, Col] = {
    "step": Col("int32", "", "time index"),
    "rx": Col("int16", "", "receiving vehicle", "vehicle"),
    "tx": Col("int8", "", "transmitter", "tx"),
    **_TX_POS,
    "ray": Col("int32", "", "ray number within (step, rx), by increasing delay"),
    "type": Col("int8", "", "landmark type of the ray (BS, VA, SP, VS, OTHER)", "type"),
    "landmark_id": Col("string", "", "landmark id (see paths.landmark_id); OTHER: '+'-joined objects"),
    "bounces": Col("int8", "", "number of interactions (0: line of sight)"),
    "a_re": Col("float64", "1", "real part of the complex path coefficient a (Sionna's Paths.a convention: "
                "field amplitude ratio rx/tx with unit-gain isotropic antennas, carrier phase "
                "exp(-j 2 pi f_c delay) NOT included; baseband gain = a exp(-j 2 pi f_c delay))"),
    "a_im": Col("float64", "1", "imaginary part of the complex path coefficient a"),
    "power_db": Col("float64", "dB", "path power 20 log10|a| (re transmit power)"),
    "delay_s": Col("float64", "s", "propagation delay (path length / c), no clock bias"),
    **{k: Col("float64", "rad", v) for k, v in _ANG.items()},
    "doppler_hz": Col("float64", "Hz", "Doppler shift (receiver and scatterer motion; positive: approaching)"),
    **_bounce_cols(),
}

PATH_SPEC: dict[str, Col] = {
    "step": Col("int32", "", "time index"),
    "rx": Col("int16", "", "receiving vehicle", "vehicle"),
    "type": Col("int8", "", "landmark type (BS, VA, SP, VS, OTHER)", "type"),
    "landmark_id": Col("string", "", "BS: 'bs'; VA: '<object>:<face>' e.g. 'wall_east:-x' or 'plane(...)', "
                       "order 2 (bounces = 2): '<first>|<second>'; SP: scatterer name; VS: vehicle name; "
                       "OTHER: '+'-joined object names of the bounces"),
    "bounces": Col("int8", "", "number of interactions (0: line of sight)"),
    "diffuse": Col("bool", "", "any diffuse bounce"),
    "toa_m": Col("float64", "m", "delay x c, no clock bias"),
    **{k: Col("float64", "rad", v) for k, v in _ANG.items()},
    "power_db": Col("float64", "dB", "power of the strongest ray of the cluster (NaN if unknown)"),
    **_TX_POS,
    "bounce_x": Col("float64", "m", "first interaction point x (NaN for LOS)"),
    "bounce_y": Col("float64", "m", "first interaction point y (NaN for LOS)"),
    "bounce_z": Col("float64", "m", "first interaction point z (NaN for LOS)"),
    "lm_x": Col("float64", "m", "ground-truth landmark x: BS position, VA image source (order 2: the "
                "image of the first image in the second plane), SP reference point, VS antenna of that "
                "vehicle at this step (NaN for OTHER)"),
    "lm_y": Col("float64", "m", "ground-truth landmark y (NaN for OTHER)"),
    "lm_z": Col("float64", "m", "ground-truth landmark z (NaN for OTHER)"),
    "n_paths": Col("int32", "", "rays merged into this row (a diffuse cluster)"),
    "delay_spread_m": Col("float64", "m", "max - min TOA of the cluster's rays (0 for a single ray)"),
    "doppler_hz": Col("float64", "Hz", "Doppler shift of the strongest ray"),
    "ray": Col("int32", "", "the strongest ray: rays.ray of the same (step, rx)"),
}

VEHICLE_COLUMNS: dict[str, str] = {k: c.dtype for k, c in VEHICLE_SPEC.items()}
RAY_COLUMNS: dict[str, str] = {k: c.dtype for k, c in RAY_SPEC.items()}
PATH_COLUMNS: dict[str, str] = {k: c.dtype for k, c in PATH_SPEC.items()}

TABLE_SPECS: dict[str, dict[str, Col]] = {"vehicles": VEHICLE_SPEC, "rays": RAY_SPEC, "paths": PATH_SPEC}
"""Table name -> column spec, in the order the cache writes them."""

ADDED_COLUMNS: dict[int, dict[str, tuple[str, ...]]] = {
    3: {"rays": TX_POSITION_COLUMNS, "paths": TX_POSITION_COLUMNS},
}
"""Schema version -> the columns it added, per table (a cache of an earlier version lacks them)."""

READABLE_SCHEMA_VERSIONS: tuple[int, ...] = (2, 3)
"""Schema versions :func:`mmslam.raytrace.cache.load_cache` reads (older ones lack what it fills in)."""


def table_columns(table: str, version: int = SCHEMA_VERSION) -> list[str]:
    """The columns of ``table`` in a cache of schema ``version`` (a readable one), in file order."""
    if version not in READABLE_SCHEMA_VERSIONS:
        raise ValueError(f"schema version {version}: expected one of {READABLE_SCHEMA_VERSIONS}")
    later = {c for v, added in ADDED_COLUMNS.items() if v > version for c in added.get(table, ())}
    return [k for k in TABLE_SPECS[table] if k not in later]


def tx_position_columns(bs: np.ndarray | tuple[float, float, float], n: int) -> dict[str, np.ndarray]:
    """The ``tx_x, tx_y, tx_z`` columns of ``n`` rows: the BS position ``bs`` ``(3,)`` m, float64."""
    b = np.asarray(bs, np.float64).reshape(3)
    return {c: np.full(n, b[j]) for j, c in enumerate(TX_POSITION_COLUMNS)}


class PathSource(Protocol):
    """Something that turns true vehicle states at one step into rays and labelled paths.

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

    def trace_tables(self, step: int, states: np.ndarray) -> dict[str, dict[str, np.ndarray]]:
        """``{"rays": ..., "paths": ...}`` for all receivers at one step.

        Args:
            step: time index.
            states: ``(n_vehicles, 7)`` true vehicle states ``[x, y, z, heading, speed,
                turn_rate, bias]`` at this step (global frame).

        Returns:
            Columns of the ``rays`` (all of :data:`RAY_COLUMNS`) and ``paths`` (all of
            :data:`PATH_COLUMNS`) tables, equal-length NumPy arrays per table (string columns
            object arrays), sorted by :func:`sort_rays` / :func:`sort_paths`.
        """
        ...

    def trace_step(self, step: int, states: np.ndarray) -> dict[str, np.ndarray]:
        """The ``paths`` table of :meth:`trace_tables`."""
        ...


def empty_table(columns: dict[str, str]) -> dict[str, np.ndarray]:
    """A zero-row column dict with the dtypes of ``columns``."""
    return {k: np.empty(0, dtype=object if t == "string" else np.dtype(t)) for k, t in columns.items()}


def empty_paths() -> dict[str, np.ndarray]:
    """A zero-row ``paths`` column dict with the schema's dtypes."""
    return empty_table(PATH_COLUMNS)


def sort_paths(cols: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Sort path columns by (step, rx, type, landmark_id), stably."""
    n = len(cols["rx"])
    if n == 0:
        return cols
    step = cols.get("step", np.zeros(n, np.int32))
    ids = np.asarray(cols["landmark_id"]).astype(str)
    order = np.lexsort((ids, cols["type"], cols["rx"], step))
    return {k: np.asarray(v)[order] for k, v in cols.items()}


def sort_rays(cols: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Sort ray columns by (step, rx, ray), stably."""
    n = len(cols["rx"])
    if n == 0:
        return cols
    step = cols.get("step", np.zeros(n, np.int32))
    order = np.lexsort((cols["ray"], cols["rx"], step))
    return {k: np.asarray(v)[order] for k, v in cols.items()}


def ray_numbers(rx: np.ndarray, delay_s: np.ndarray, tiebreak: np.ndarray | None = None) -> np.ndarray:
    """``ray`` numbers: rank of each ray within its receiver by (delay, ``tiebreak``), int32 ``(n,)``."""
    rx = np.asarray(rx, np.int64)
    n = rx.size
    if n == 0:
        return np.zeros(0, np.int32)
    keys = (np.asarray(delay_s, float), rx) if tiebreak is None else (tiebreak, np.asarray(delay_s, float), rx)
    order = np.lexsort(keys)
    rs = rx[order]
    starts = np.flatnonzero(np.r_[True, rs[1:] != rs[:-1]])
    rank = np.arange(n) - np.repeat(starts, np.diff(np.r_[starts, n]))
    out = np.empty(n, np.int32)
    out[order] = rank
    return out


def rays_columns(*, step: int, rx: np.ndarray, typ: np.ndarray, landmark_id: np.ndarray, a: np.ndarray,
                 delay_s: np.ndarray, angles: np.ndarray, doppler_hz: np.ndarray, itype: np.ndarray,
                 objects: np.ndarray, verts: np.ndarray, ray: np.ndarray,
                 tx_pos: np.ndarray | tuple[float, float, float]) -> dict[str, np.ndarray]:
    """Assemble the ``rays`` table of one step.

    Args:
        step: time index.
        tx_pos: ``(3,)`` transmitter (BS) position, m, global frame.
        rx: ``(n,)`` receiver index. typ: ``(n,)`` type code. landmark_id: ``(n,)`` str.
        a: ``(n,)`` complex path coefficient. delay_s: ``(n,)`` s.
        angles: ``(n, 4)`` ``[aod_az, aod_el, aoa_az, aoa_el]`` rad. doppler_hz: ``(n,)`` Hz.
        itype: ``(n, D)`` interaction codes (:data:`INTERACTION_LABELS` index), ``D <= 3``.
        objects: ``(n, D)`` object names ('' for none). verts: ``(n, D, 3)`` m.
        ray: ``(n,)`` ray numbers (:func:`ray_numbers`).

    Returns:
        ``rays`` columns (all of :data:`RAY_COLUMNS`), sorted by :func:`sort_rays`.
    """
    rx = np.asarray(rx)
    n = rx.size
    a = np.asarray(a, complex).reshape(n)
    itype = np.asarray(itype, np.int64)
    # (n, D); with no path at all (n = 0) reshape(0, -1) cannot infer D: keep the given width
    itype = itype.reshape(n, itype.shape[-1] if n == 0 and itype.ndim == 2 else (-1 if n else 0))
    D = itype.shape[1]
    if D > MAX_BOUNCES:
        raise ValueError(f"rays_columns: {D} interaction slots, the schema holds {MAX_BOUNCES}")
    objects = np.asarray(objects, dtype=object).reshape(n, D)
    verts = np.asarray(verts, float).reshape(n, D, 3)
    angles = np.asarray(angles, float).reshape(n, 4)
    used = itype != 0
    with np.errstate(divide="ignore"):
        power = 20.0 * np.log10(np.abs(a))
    cols: dict[str, np.ndarray] = {
        "step": np.full(n, step, np.int32), "rx": rx.astype(np.int16), "tx": np.zeros(n, np.int8),
        **tx_position_columns(tx_pos, n),
        "ray": np.asarray(ray, np.int32), "type": np.asarray(typ, np.int8),
        "landmark_id": np.asarray(landmark_id, dtype=object), "bounces": used.sum(axis=1).astype(np.int8),
        "a_re": a.real.copy(), "a_im": a.imag.copy(), "power_db": power, "delay_s": np.asarray(delay_s, float),
        "aod_az": angles[:, 0], "aod_el": angles[:, 1], "aoa_az": angles[:, 2], "aoa_el": angles[:, 3],
        "doppler_hz": np.asarray(doppler_hz, float),
    }
    for k in range(MAX_BOUNCES):
        has = used[:, k] if k < D else np.zeros(n, bool)
        cols[f"bounce{k + 1}_type"] = (itype[:, k] if k < D else np.zeros(n)).astype(np.int8)
        cols[f"bounce{k + 1}_object"] = np.where(has, objects[:, k] if k < D else "", "").astype(object)
        for j, c in enumerate("xyz"):
            cols[f"bounce{k + 1}_{c}"] = np.where(has, verts[:, k, j] if k < D else np.nan, np.nan)
    return sort_rays({k: np.asarray(cols[k], dtype=object if t == "string" else np.dtype(t))
                      for k, t in RAY_COLUMNS.items()})


def schema_markdown() -> str:
    """Markdown tables of every column (name, dtype on disk, unit, meaning), as in ``docs/dataset.md``."""
    lines = []
    labels = {"type": ", ".join(TYPE_LABELS), "interaction": ", ".join(INTERACTION_LABELS),
              "tx": ", ".join(TX_LABELS), "vehicle": "the vehicle names"}
    for table, spec in TABLE_SPECS.items():
        lines += [f"### `{table}`", "", "| column | type | unit | meaning |", "|---|---|---|---|"]
        for k, c in spec.items():
            typ = f"dictionary ({labels[c.enum]})" if c.enum else c.dtype
            lines.append(f"| `{k}` | {typ} | {c.unit or '-'} | {c.doc} |")
        lines.append("")
    return "\n".join(lines)
