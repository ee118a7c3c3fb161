"""The resumable Parquet path cache (docs/design.md section 7, tables in :mod:`mmslam.raytrace.schema`).

A cache is a directory ``<root>/<scenario>-<source>-<confighash>`` holding

- ``manifest.json``: ``schema_version``, ``scenario`` (name), ``geometry_hash``, ``config_hash``
  (SHA-256 of geometry hash, source name and source settings), ``source``, ``versions``
  (library versions), ``settings`` (solver settings), ``resolved_scenario``
  (:meth:`Scenario.to_dict`), ``scenario_settings`` (the parameter tables the scenario's own file
  sets, or null) and ``settings_defaults`` (the parameter defaults of the mmslam that wrote it): read
  back, the parameters the scenario left open take this mmslam's defaults
  (:func:`~mmslam.scenes.scenario.refresh_settings`), ``vehicle_names``, ``dt`` [s], ``steps_completed``,
  ``steps_requested``, ``chunks`` (list of ``{index, step_start, step_stop, files: {vehicles,
  rays, paths}, sha256: {...}, rows: {...}, versions}``, ``step_stop`` exclusive; ``files`` are
  relative paths; ``versions`` = library versions of the run that wrote the chunk);
- one directory per table (``vehicles/``, ``rays/``, ``paths/``; schema in
  :mod:`mmslam.raytrace.schema`) holding ``part-NNNNN.parquet``, one file per chunk of
  consecutive steps. Each directory is one dataset: ``pandas.read_parquet(CACHE / "rays")``,
  ``pyarrow.dataset.dataset(CACHE / "rays")`` or duckdb ``read_parquet('CACHE/rays/*.parquet')``.
  Enum columns (``type``, ``rx``, ``vehicle``, ``tx``, ``bounceK_type``) are Arrow dictionaries
  of their labels; every field has ``unit`` and ``doc`` metadata; the file metadata key
  ``mmslam`` holds a JSON object with the table name, schema version, scenario (name and
  resolved parameters), source, solver settings, config hash, frame and units conventions.

Schema versions: this mmslam writes :data:`~mmslam.raytrace.schema.SCHEMA_VERSION` (3) and reads
:data:`~mmslam.raytrace.schema.READABLE_SCHEMA_VERSIONS`. A version-2 cache (no transmitter
position columns) loads with ``tx_x, tx_y, tx_z`` filled in memory from the manifest's
``resolved_scenario.bs``; its files are never rewritten, and a resumed or extended version-2
trace writes its new chunks in version 2 too, so one cache holds one version. The config hash
does not hold the schema version: the traced content of a version-2 and a version-3 cache of
one configuration is the same, so a version-3 mmslam keeps using (and extending) the older
cache instead of re-tracing it.

Every file is written to a temporary name in the same directory and renamed into place
(:func:`atomic_write_bytes`); the manifest is rewritten (atomically) after each chunk, so a
killed trace loses at most the chunk in progress. :func:`load_cache` validates everything it
reads and raises a one-line :class:`~mmslam.errors.CacheError` (CLI exit code 2) otherwise.
"""
from __future__ import annotations

import dataclasses
import hashlib
import io
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from mmslam.errors import CacheError, MmslamError
from mmslam.outputs import atomic_write_bytes
from mmslam.raytrace.schema import (
    INTERACTION_LABELS, PATH_COLUMNS, RAY_COLUMNS, READABLE_SCHEMA_VERSIONS, SCHEMA_VERSION, TABLE_SPECS,
    TX_LABELS, TX_POSITION_COLUMNS, TYPE_LABELS, VEHICLE_COLUMNS, Col, sort_paths, sort_rays, table_columns,
    tx_position_columns,
)
from mmslam.scenes.scenario import Scenario, default_settings, refresh_settings, scenario_from_resolved
from mmslam.model import BS, OTHER

MANIFEST = "manifest.json"
FORCE_HINT = "re-run `mmslam trace ... --force` to rebuild it"
TABLES = tuple(TABLE_SPECS)  # ("vehicles", "rays", "paths")
FRAME_DOC = ("global frame: x east, y north, z up, metres; angles in radians, azimuth from +x towards +y, "
             "elevation above the xy plane; AOA azimuth not heading-corrected; time t = step * dt seconds")

# Numeric path columns that may hold NaN, and for which rows (None: any row).
_NAN_ALLOWED: dict[str, int | None] = {
    "bounce_x": BS, "bounce_y": BS, "bounce_z": BS,
    "lm_x": OTHER, "lm_y": OTHER, "lm_z": OTHER,
    "power_db": None, "doppler_hz": None,
}


# ====================================================================== hashing / naming
def config_hash(scn: Scenario, source_name: str, settings: dict) -> str:
    """SHA-256 (hex, 16 chars) of the geometry hash, the source name and its solver settings."""
    blob = json.dumps({"geometry": scn.geometry_hash(), "source": source_name, "settings": settings},
                      sort_keys=True, default=str).encode()
    return hashlib.sha256(blob).hexdigest()[:16]


def cache_dir_for(root: str | Path, scn: Scenario, source: Any) -> Path:
    """The cache directory of ``scn`` traced by ``source``: ``root/<name>-<source>-<confighash>``.

    Any change to the traced geometry, the source or its settings changes the directory, so a
    different configuration never reads a stale cache.
    """
    return Path(root) / f"{scn.name}-{source.name}-{config_hash(scn, source.name, source.settings())}"


def sha256_file(path: Path) -> str:
    """Hex SHA-256 of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


# ====================================================================== atomic writes
def write_manifest(cache_dir: Path, manifest: dict) -> None:
    """Atomically (re)write ``manifest.json``."""
    atomic_write_bytes(Path(cache_dir) / MANIFEST,
                       (json.dumps(manifest, indent=1, sort_keys=True) + "\n").encode())


def remove_temp_files(cache_dir: Path) -> None:
    """Delete leftovers of interrupted atomic writes (``.*.tmp``) in ``cache_dir`` and its table directories."""
    for d in (Path(cache_dir), *(Path(cache_dir) / t for t in TABLES)):
        for p in d.glob(".*.tmp"):
            p.unlink(missing_ok=True)


def enum_labels(enum: str, vehicle_names: list[str] | tuple[str, ...]) -> tuple[str, ...]:
    """Labels of an enum column: ``type``, ``interaction``, ``tx`` or ``vehicle`` (the vehicle names)."""
    return {"type": TYPE_LABELS, "interaction": INTERACTION_LABELS, "tx": TX_LABELS,
            "vehicle": tuple(vehicle_names)}[enum]


def to_arrow(table: str, cols: dict[str, np.ndarray], meta: dict, version: int = SCHEMA_VERSION) -> pa.Table:
    """One table's columns as a self-describing Arrow table of schema ``version``.

    Enum columns become ``dictionary<int16, string>`` arrays of their labels, every field gets
    ``unit`` and ``doc`` metadata, and ``meta`` (JSON-able; must hold ``vehicle_names``) goes to
    the schema metadata key ``mmslam`` together with the table name, schema version and frame.
    ``version`` < :data:`SCHEMA_VERSION` (extending an older cache) leaves out the columns later
    versions added (:func:`~mmslam.raytrace.schema.table_columns`).
    """
    spec: dict[str, Col] = TABLE_SPECS[table]
    fields, arrays = [], []
    for k in table_columns(table, version):
        c = spec[k]
        v = np.asarray(cols[k])
        if c.enum is not None:
            labels = enum_labels(c.enum, meta["vehicle_names"])
            codes = v.astype(np.int64)
            if codes.size and (codes.min() < 0 or codes.max() >= len(labels)):
                raise ValueError(f"{table}.{k}: code {int(codes.max())} outside its {len(labels)} labels")
            arr = pa.DictionaryArray.from_arrays(pa.array(codes.astype(np.int16), pa.int16()),
                                                 pa.array(list(labels), pa.string()))
        elif c.dtype == "string":
            arr = pa.array(v.astype(str).tolist(), type=pa.string())
        else:
            arr = pa.array(v.astype(c.dtype), type=pa.from_numpy_dtype(np.dtype(c.dtype)))
        fields.append(pa.field(k, arr.type, metadata={"unit": c.unit, "doc": c.doc}))
        arrays.append(arr)
    info = {"table": table, "schema_version": version, "frame": FRAME_DOC, **meta}
    schema = pa.schema(fields, metadata={"mmslam": json.dumps(info, sort_keys=True, default=str)})
    return pa.Table.from_arrays(arrays, schema=schema)


def table_bytes(table: str, cols: dict[str, np.ndarray], meta: dict, version: int = SCHEMA_VERSION) -> bytes:
    """Serialise one table's columns to Parquet bytes (deterministic: same input, same bytes)."""
    buf = io.BytesIO()
    pq.write_table(to_arrow(table, cols, meta, version), buf, compression="zstd", write_statistics=False)
    return buf.getvalue()


def vehicle_columns(states: np.ndarray, step_start: int, dt: float) -> dict[str, np.ndarray]:
    """``vehicles`` table columns from states ``(n_steps, n_veh, 7)`` starting at ``step_start``."""
    ns, nv = states.shape[:2]
    step = np.repeat(np.arange(step_start, step_start + ns), nv)
    sp, h = states[:, :, 4].ravel(), states[:, :, 3].ravel()
    return {
        "step": step.astype(np.int32), "t": step * dt, "vehicle": np.tile(np.arange(nv), ns).astype(np.int16),
        "x": states[:, :, 0].ravel(), "y": states[:, :, 1].ravel(), "z": states[:, :, 2].ravel(),
        "heading": h, "speed": sp, "turn_rate": states[:, :, 5].ravel(),
        "vx": sp * np.cos(h), "vy": sp * np.sin(h), "vz": np.zeros(ns * nv),
    }


def file_metadata(m: dict) -> dict:
    """What every Parquet file of a cache carries in its ``mmslam`` metadata, from the manifest ``m``."""
    return {k: m[k] for k in ("scenario", "source", "settings", "config_hash", "geometry_hash",
                              "vehicle_names", "dt", "resolved_scenario") if k in m}


def write_chunk(cache_dir: Path, index: int, step_start: int, tables: dict[str, dict[str, np.ndarray]],
                meta: dict, version: int = SCHEMA_VERSION) -> dict:
    """Write one chunk (``tables``: vehicles, rays, paths columns) atomically; return its manifest entry.

    ``meta``: :func:`file_metadata` of the manifest (must hold ``vehicle_names``); ``version``: the
    cache's schema version (the manifest's ``schema_version``).
    """
    entry: dict[str, Any] = {"index": index, "step_start": step_start,
                             "step_stop": step_start + len(np.unique(tables["vehicles"]["step"])),
                             "files": {}, "sha256": {}, "rows": {}}
    for table in TABLES:
        cols = tables[table]
        name = f"{table}/part-{index:05d}.parquet"
        data = table_bytes(table, cols, meta, version)
        (Path(cache_dir) / table).mkdir(exist_ok=True)
        atomic_write_bytes(Path(cache_dir) / name, data)
        entry["files"][table] = name
        entry["sha256"][table] = hashlib.sha256(data).hexdigest()
        entry["rows"][table] = len(cols["step"])
    return entry


# ====================================================================== reading
@dataclass
class PathCache:
    """A loaded, validated path cache.

    Attributes:
        path: the cache directory.
        manifest: the parsed ``manifest.json``.
        scenario: the resolved scenario the cache was traced from, with ``steps`` set to the
            number of steps the cache holds (the trace may be shorter or longer than the
            scenario file's ``steps``), and this mmslam's defaults for the parameters its scenario
            left open (:func:`~mmslam.scenes.scenario.refresh_settings`).
        vehicle_names: receiver / vehicle names (index = ``vehicle`` / ``rx`` column).
        states: ``(steps, n_veh, 7)`` true states ``[x, y, z, heading, speed, turn_rate, bias]``
            (m, m, m, rad, m/s, rad/s, m); ``bias`` is each vehicle's initial clock bias.
        vehicles: ``vehicles`` table columns (all chunks, sorted by step, vehicle).
        paths: ``paths`` table columns (all chunks, sorted by step, rx, type, landmark_id;
            ``landmark_id`` an object array of ``str``).
        steps: number of completed steps.
        settings_known: whether the manifest records which parameters the scenario set (caches traced
            before that keep every stored parameter, old defaults included).
        settings_changed: ``"section.key: old -> new"`` for each parameter now at this mmslam's default
            instead of the stored one.

    Enum columns are integer codes in memory (``rx``/``vehicle``: index into ``vehicle_names``;
    ``type``: BS=0 .. OTHER=4). The ``rays`` table is read on demand by :meth:`read_rays`.
    """

    path: Path
    manifest: dict
    scenario: Scenario
    vehicle_names: list[str]
    states: np.ndarray
    vehicles: dict[str, np.ndarray]
    paths: dict[str, np.ndarray]
    steps: int
    _rays: dict[str, np.ndarray] | None = None
    settings_known: bool = True
    settings_changed: tuple[str, ...] = ()

    def partial_notice(self) -> str | None:
        """One line when the cache holds fewer steps than its trace was asked for (``steps_requested``: a trace that
        stopped early), else None."""
        done, want = int(self.states.shape[0]), self.manifest.get("steps_requested")
        if not isinstance(want, int) or done >= want:
            return None
        return (f"note: {self.path.name} holds {done} of the {want} steps its trace was asked for (it stopped "
                f"early): the run covers those {done}; run mmslam trace on its scenario with the same --out to "
                "complete it")

    def settings_notice(self) -> str | None:
        """One line for the user when the settings differ from those stored at trace time, or when the
        cache cannot tell and its stored settings differ from this mmslam's defaults; else None."""
        if self.settings_changed:
            shown = "; ".join(self.settings_changed[:3]) + (" ..." if len(self.settings_changed) > 3 else "")
            return (f"note: {self.path.name}: {len(self.settings_changed)} setting(s) differ from those stored when "
                    f"it was traced (what its scenario leaves open follows this mmslam's defaults, what its preset "
                    f"has set since follows the preset): {shown}")
        if not self.settings_known:
            stored, now = self.scenario.to_dict(), default_settings()
            if any(stored.get(s) != now[s] for s in ("filter", "fusion", "evaluation")):
                return (f"note: {self.path.name} does not record which settings its scenario set (traced by an "
                        "older mmslam): running with the settings stored then; `mmslam trace` its scenario again "
                        "(the paths are reused) to take this version's defaults, or give them with --set")
        return None

    def read_rays(self) -> dict[str, np.ndarray]:
        """The ``rays`` table (all chunks, sorted by step, rx, ray; validated), read once and kept."""
        if self._rays is None:
            parts = [_read_table(self.path / c["files"]["rays"], c["sha256"]["rays"], "rays", self.vehicle_names,
                                 version=int(self.manifest["schema_version"]), bs=self.scenario.bs_array)
                     for c in self.manifest["chunks"]]
            rays = sort_rays(_concat(parts, RAY_COLUMNS))
            for k in ("delay_s", "a_re", "a_im", "aod_az", "aod_el", "aoa_az", "aoa_el", "doppler_hz"):
                bad = ~np.isfinite(rays[k])
                if bad.any():
                    raise CacheError(f"{self.path}: rays column '{k}' is not finite at step "
                                     f"{int(rays['step'][np.argmax(bad)])}; {FORCE_HINT}")
            d = rays["delay_s"]
            bad = (d <= 0) | (d > MAX_LENGTH_M / 299_792_458.0)  # c = 299 792 458 m/s
            if bad.any():
                raise CacheError(f"{self.path}: rays column 'delay_s' is {d[np.argmax(bad)]} at step "
                                 f"{int(rays['step'][np.argmax(bad)])}, expected a delay in (0, "
                                 f"{MAX_LENGTH_M:g} m / c]; {FORCE_HINT}")
            st, rx, ray = rays["step"], rays["rx"], rays["ray"]  # sorted by (step, rx, ray)
            dup = (st[1:] == st[:-1]) & (rx[1:] == rx[:-1]) & (ray[1:] == ray[:-1])
            if dup.any():
                i = int(np.argmax(dup))
                raise CacheError(f"{self.path}: two rays numbered {int(ray[i])} at step {int(st[i])}, rx {int(rx[i])} "
                                 f"(a duplicated row); {FORCE_HINT}")
            self._rays = rays
        return self._rays


def list_caches(root: str | Path) -> list[Path]:
    """The cache directories directly under ``root`` (sorted; ``[]`` if none)."""
    p = Path(root)
    return sorted(d for d in p.iterdir() if (d / MANIFEST).is_file()) if p.is_dir() else []


def _cache_source(d: Path) -> str | None:
    try:
        return str(json.loads((d / MANIFEST).read_text()).get("source"))
    except (OSError, ValueError, AttributeError):
        return None


def find_cache_dir(path: str | Path, source: str | None = None) -> Path:
    """``path`` itself if it holds a manifest, else its only sub-directory that does.

    With ``source`` (``sionna`` / ``analytic``), the only sub-directory traced by that source.
    """
    p = Path(path)
    if p.exists() and not p.is_dir():
        raise CacheError(f"{p}: is a file, not a cache folder; give the folder `mmslam trace --out` wrote, or one "
                         "cache folder in it")
    if not p.is_dir():
        raise CacheError(f"{p}: no such cache directory; run `mmslam trace <scenario> --out {p}` first")
    if (p / MANIFEST).is_file():
        return p
    cands = list_caches(p)
    if source is not None:
        cands = [c for c in cands if _cache_source(c) == source]
    if len(cands) == 1:
        return cands[0]
    if not cands:
        what = f"cache traced by '{source}'" if source is not None else MANIFEST
        deeper = [c for d in sorted(p.iterdir()) if d.is_dir() for c in list_caches(d)
                  if source is None or _cache_source(c) == source]
        if deeper:  # e.g. an ablation's folder, whose caches are in its cache/ folder
            found = f"{', '.join(str(c) for c in deeper[:2])}{' ...' if len(deeper) > 2 else ''}"
            raise CacheError(f"{p}: no {what} here or directly under it, but {len(deeper)} "
                             f"cache{'s' if len(deeper) > 1 else ''} a level further down ({found}); give "
                             f"{'one of them' if len(deeper) > 1 else 'that folder'}")
        raise CacheError(f"{p}: no {what} here or directly under it; run `mmslam trace` to create a cache")
    raise CacheError(f"{p}: holds {len(cands)} caches ({', '.join(c.name for c in cands)}); give one of them")


def read_manifest(cache_dir: Path) -> dict:
    """Parse and check ``manifest.json`` (schema version, required keys)."""
    mp = Path(cache_dir) / MANIFEST
    if not mp.is_file():
        raise CacheError(f"{mp}: missing; {FORCE_HINT}")
    try:
        m = json.loads(mp.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise CacheError(f"{mp}: not valid JSON ({e.__class__.__name__}); {FORCE_HINT}") from None
    except RecursionError:
        raise CacheError(f"{mp}: nested too deeply to be a manifest; {FORCE_HINT}") from None
    if not isinstance(m, dict):
        raise CacheError(f"{mp}: not a JSON object; {FORCE_HINT}")
    v = m.get("schema_version")
    if not (_is_int(v) and v in READABLE_SCHEMA_VERSIONS):
        old = _is_int(v) and v < min(READABLE_SCHEMA_VERSIONS)
        newer = _is_int(v) and v > SCHEMA_VERSION
        why = (" (an older cache: no rays table, gains, Doppler or column metadata)" if old
               else " (written by a newer mmslam)" if newer else "")
        hint = f"upgrade mmslam to read it, or {FORCE_HINT}" if newer else FORCE_HINT
        raise CacheError(f"{mp}: schema_version {v!r}{why}, this mmslam reads "
                         f"{' and '.join(map(str, READABLE_SCHEMA_VERSIONS))}; {hint}")
    need = ("scenario", "config_hash", "source", "resolved_scenario", "vehicle_names", "dt",
            "steps_completed", "chunks")
    miss = [k for k in need if k not in m]
    if miss:
        raise CacheError(f"{mp}: missing keys {miss}; {FORCE_HINT}")
    _check_manifest_types(m, mp)
    return m


def _is_int(v: Any, lo: int = 0) -> bool:
    return isinstance(v, int) and not isinstance(v, bool) and v >= lo


def _check_manifest_types(m: dict, mp: Path) -> None:
    """Raise a one-line :class:`CacheError` naming the first manifest value of the wrong type or range.

    Everything later code indexes or converts: ``scenario``, ``config_hash``, ``source`` (strings),
    ``resolved_scenario`` (an object), ``vehicle_names`` (non-empty list of strings), ``dt`` (> 0),
    ``steps_completed`` (integer >= 0), ``chunks`` (a list of objects with integer ``index``,
    ``step_start`` < ``step_stop``, and per table a file ``<table>/part-NNNNN.parquet``, a sha256
    string and a row count).
    """
    def bad(key: str, value: Any, expected: str) -> CacheError:
        shown = json.dumps(value)
        shown = shown if len(shown) <= 40 else shown[:37] + "..."
        return CacheError(f"{mp}: '{key}' is {shown}, expected {expected}; {FORCE_HINT}")

    for k in ("scenario", "config_hash", "source"):
        if not isinstance(m[k], str):
            raise bad(k, m[k], "a string")
    if not isinstance(m["resolved_scenario"], dict):
        raise bad("resolved_scenario", m["resolved_scenario"], "an object")
    names = m["vehicle_names"]
    if not (isinstance(names, list) and names and all(isinstance(n, str) for n in names)):
        raise bad("vehicle_names", names, "a non-empty list of names")
    dt = m["dt"]
    if isinstance(dt, bool) or not isinstance(dt, (int, float)) or not 0 < dt < float("inf"):
        raise bad("dt", dt, "a time step > 0 s")
    if not _is_int(m["steps_completed"]):
        raise bad("steps_completed", m["steps_completed"], "an integer >= 0")
    if not isinstance(m["chunks"], list):
        raise bad("chunks", m["chunks"], "a list of chunk entries")
    for i, c in enumerate(m["chunks"]):
        where = f"chunks[{i}]"
        if not isinstance(c, dict):
            raise bad(where, c, "an object")
        for k in ("index", "step_start", "step_stop"):
            if not _is_int(c.get(k)):
                raise bad(f"{where}.{k}", c.get(k), "an integer >= 0")
        if c["step_stop"] <= c["step_start"]:
            raise bad(f"{where}.step_stop", c["step_stop"], f"a step after step_start {c['step_start']}")
        for k in ("files", "sha256", "rows"):
            if not isinstance(c.get(k), dict):
                raise bad(f"{where}.{k}", c.get(k), "an object with one entry per table")
        for t in TABLES:
            f = c["files"].get(t)
            if not (isinstance(f, str) and f.startswith(f"{t}/part-") and f.endswith(".parquet") and "/" not in f[len(t) + 1:]
                    and ".." not in f):
                raise bad(f"{where}.files.{t}", f, f"a file {t}/part-NNNNN.parquet")
            if not isinstance(c["sha256"].get(t), str):
                raise bad(f"{where}.sha256.{t}", c["sha256"].get(t), "a sha256 hex string")
            if not _is_int(c["rows"].get(t)):
                raise bad(f"{where}.rows.{t}", c["rows"].get(t), "an integer >= 0")


def checked_chunks(m: dict, mp: Path) -> list[dict]:
    """The manifest's chunks, checked to run contiguously from step 0 to ``steps_completed``.

    Raises :class:`CacheError` naming the manifest ``mp`` on a gap, an overlap or a mismatch.
    """
    expect = 0
    for c in m["chunks"]:
        if c["step_start"] != expect:
            raise CacheError(f"{mp}: chunk {c['index']} starts at step {c['step_start']}, expected "
                             f"{expect}; {FORCE_HINT}")
        expect = c["step_stop"]
    if expect != int(m["steps_completed"]):
        raise CacheError(f"{mp}: chunks cover {expect} steps but steps_completed is "
                         f"{m['steps_completed']}; {FORCE_HINT}")
    return list(m["chunks"])


def check_tx_columns(cols: dict[str, np.ndarray], bs: np.ndarray, where: str, hint: str = FORCE_HINT) -> None:
    """Raise a one-line :class:`CacheError` unless every row's ``tx_x, tx_y, tx_z`` is the BS position.

    Args:
        cols: ``rays`` or ``paths`` columns (with ``step``, ``rx`` and the transmitter columns).
        bs: ``(3,)`` the scenario's BS position, m. Every path source writes it as is (float64), so
            the test is equality; a NaN fails it too.
        where: the file or source named in the message.
    """
    b = np.asarray(bs, np.float64).reshape(3)
    for j, k in enumerate(TX_POSITION_COLUMNS):
        bad = cols[k] != b[j]
        if bad.any():
            i = int(np.argmax(bad))
            raise CacheError(f"{where}: column '{k}' is {float(cols[k][i])!r} at step {int(cols['step'][i])} (rx "
                             f"{int(cols['rx'][i])}), expected the BS position {float(b[j])!r} m of the scenario "
                             f"(resolved_scenario.bs); {hint}")


def _read_table(path: Path, expect_sha: str, table: str, vehicle_names: list[str], *, version: int,
                bs: np.ndarray) -> dict[str, np.ndarray]:
    """Read and check one Parquet file of ``table`` in a cache of schema ``version``.

    Enum columns come back as integer codes. The transmitter columns (``rays``, ``paths``) must
    equal the BS position ``bs`` ``(3,)`` m (:func:`check_tx_columns`); a version-2 file lacks
    them and gets them filled from ``bs`` (in memory; the file is not touched). The result holds
    every column of the current schema, in its order.
    """
    spec: dict[str, Col] = TABLE_SPECS[table]
    names = table_columns(table, version)
    if not path.is_file():
        raise CacheError(f"{path}: chunk file missing; {FORCE_HINT}")
    data = path.read_bytes()
    if hashlib.sha256(data).hexdigest() != expect_sha:
        raise CacheError(f"{path}: sha256 mismatch (truncated or modified); {FORCE_HINT}")
    try:
        # ParquetFile.read: ~2x less per-file overhead than read_table's dataset layer (small chunks)
        tbl = pq.ParquetFile(pa.BufferReader(data)).read(use_threads=False)
    except Exception as e:  # pyarrow raises several types for corrupt files
        raise CacheError(f"{path}: unreadable Parquet ({e.__class__.__name__}); {FORCE_HINT}") from None
    if tbl.column_names != names:
        raise CacheError(f"{path}: columns {tbl.column_names} differ from those of schema version {version} {names}; "
                         f"{FORCE_HINT}")
    out = {}
    for k in names:
        c = spec[k]
        col = tbl.column(k)
        if c.enum is not None:
            if not pa.types.is_dictionary(col.type):
                raise CacheError(f"{path}: column '{k}' is {col.type}, expected a dictionary of labels; {FORCE_HINT}")
            labels = enum_labels(c.enum, vehicle_names)
            codes = np.empty(len(col), np.int64)
            pos = 0
            for ch in col.chunks:
                lut = {lab: i for i, lab in enumerate(labels)}
                dic = ch.dictionary.to_pylist()
                unknown = [d for d in dic if d not in lut]
                if unknown:
                    raise CacheError(f"{path}: column '{k}' has labels {unknown} not in {list(labels)}; {FORCE_HINT}")
                m = np.array([lut[d] for d in dic], np.int64)
                idx = ch.indices.to_numpy(zero_copy_only=False)
                codes[pos:pos + len(ch)] = m[idx] if len(idx) else idx
                pos += len(ch)
            out[k] = codes.astype(c.dtype)
        elif c.dtype == "string":
            out[k] = np.asarray(col.to_numpy(zero_copy_only=False), dtype=object)
        else:
            arr = col.to_numpy()
            if arr.dtype != np.dtype(c.dtype):
                raise CacheError(f"{path}: column '{k}' has dtype {arr.dtype}, expected {c.dtype}; {FORCE_HINT}")
            out[k] = arr
    if TX_POSITION_COLUMNS[0] in spec:
        if TX_POSITION_COLUMNS[0] in names:
            check_tx_columns(out, bs, str(path))
        else:  # an older schema: the BS position of the manifest, the value a version-3 trace writes
            out.update(tx_position_columns(bs, tbl.num_rows))
    return {k: out[k] for k in spec}


def _concat(parts: list[dict[str, np.ndarray]], schema: dict[str, str]) -> dict[str, np.ndarray]:
    if not parts:
        return {k: np.empty(0, dtype=object if t == "string" else np.dtype(t)) for k, t in schema.items()}
    return {k: np.concatenate([p[k] for p in parts]) for k in schema}


def check_paths_finite(paths: dict[str, np.ndarray], where: str, hint: str = FORCE_HINT) -> None:
    """Raise :class:`CacheError` naming the column and step of the first forbidden NaN / inf.

    Allowed NaN: ``bounce_*`` on LOS rows, ``lm_*`` on OTHER rows, ``power_db`` and ``doppler_hz``
    anywhere (unknown).
    """
    typ = paths["type"]
    for k, t in PATH_COLUMNS.items():
        if t in ("string", "bool") or not np.issubdtype(np.dtype(t), np.floating):
            continue
        v = paths[k]
        if k not in _NAN_ALLOWED:
            bad = ~np.isfinite(v)
        elif _NAN_ALLOWED[k] is None:
            bad = np.isinf(v)
        else:
            bad = np.isinf(v) | (np.isnan(v) & (typ != _NAN_ALLOWED[k]))
        if bad.any():
            i = int(np.argmax(bad))
            raise CacheError(f"{where}: column '{k}' is {v[i]} at step {int(paths['step'][i])} "
                             f"(rx {int(paths['rx'][i])}, landmark '{paths['landmark_id'][i]}'); {hint}")


MAX_LENGTH_M = 1e7
"""Largest physical path length / TOA / delay spread accepted on load (m): far above any scene
(coordinates are bounded by :data:`mmslam.limits.COORD_MAX` = 1e6 m), low enough to refuse an edited 1e300."""
MAX_DOPPLER_HZ = 1e7
"""Largest |Doppler| accepted on load (Hz): 1000 m/s at 3 THz is 1e7 Hz."""
_ANGLE_TOL = 1e-6


def _first_bad(paths: dict[str, np.ndarray], bad: np.ndarray, k: str, where: str, expected: str, hint: str) -> None:
    if bad.any():
        i = int(np.argmax(bad))
        raise CacheError(f"{where}: column '{k}' is {paths[k][i]} at step {int(paths['step'][i])} "
                         f"(rx {int(paths['rx'][i])}), expected {expected}; {hint}")


def check_paths_physical(paths: dict[str, np.ndarray], where: str, hint: str = FORCE_HINT) -> None:
    """Raise :class:`CacheError` on the first path value outside its physical range, or a duplicated row.

    Ranges: ``0 < toa_m <= MAX_LENGTH_M``, ``0 <= delay_spread_m <= MAX_LENGTH_M``, azimuths in
    ``[-pi, pi]``, elevations in ``[-pi/2, pi/2]``, ``|doppler_hz| <= MAX_DOPPLER_HZ``, ``bounces >= 0``,
    ``n_paths >= 1``, ``ray >= 0``, coordinates within ``COORD_MAX``. Unique: ``(step, rx, ray)`` (a
    ray is the strongest of one path row). NaN passes here (:func:`check_paths_finite` decides).
    Vectorised, O(n log n) for the uniqueness sort.
    """
    from mmslam.limits import COORD_MAX

    with np.errstate(invalid="ignore"):
        toa = paths["toa_m"]
        _first_bad(paths, ~((toa > 0) & (toa <= MAX_LENGTH_M)), "toa_m", where, f"a path length in (0, {MAX_LENGTH_M:g}] m", hint)
        ds = paths["delay_spread_m"]
        _first_bad(paths, (ds < 0) | (ds > MAX_LENGTH_M), "delay_spread_m", where, f"0 .. {MAX_LENGTH_M:g} m", hint)
        for k in ("aod_az", "aoa_az"):
            _first_bad(paths, np.abs(paths[k]) > np.pi + _ANGLE_TOL, k, where, "an azimuth in [-pi, pi] rad", hint)
        for k in ("aod_el", "aoa_el"):
            _first_bad(paths, np.abs(paths[k]) > np.pi / 2 + _ANGLE_TOL, k, where,
                       "an elevation in [-pi/2, pi/2] rad", hint)
        _first_bad(paths, np.abs(paths["doppler_hz"]) > MAX_DOPPLER_HZ, "doppler_hz", where,
                   f"|Doppler| <= {MAX_DOPPLER_HZ:g} Hz", hint)
        for k in ("bounce_x", "bounce_y", "bounce_z", "lm_x", "lm_y", "lm_z"):
            _first_bad(paths, np.abs(paths[k]) > COORD_MAX, k, where, f"a coordinate within +-{COORD_MAX:g} m", hint)
    for k, lo in (("bounces", 0), ("n_paths", 1), ("ray", 0)):
        _first_bad(paths, paths[k] < lo, k, where, f">= {lo}", hint)
    n = len(paths["step"])
    if n > 1:
        key = np.lexsort((paths["ray"], paths["rx"], paths["step"]))
        st, rx, ray = paths["step"][key], paths["rx"][key], paths["ray"][key]
        dup = (st[1:] == st[:-1]) & (rx[1:] == rx[:-1]) & (ray[1:] == ray[:-1])
        if dup.any():
            i = int(key[1:][np.argmax(dup)])
            raise CacheError(f"{where}: two path rows for step {int(paths['step'][i])}, rx {int(paths['rx'][i])}, "
                             f"ray {int(paths['ray'][i])} (a duplicated row; each ray heads one path); {hint}")


def load_cache(path: str | Path) -> PathCache:
    """Load and validate a path cache.

    Args:
        path: a cache directory, or a root directory holding exactly one cache.

    Raises:
        CacheError: missing directory / manifest, no traced step, a schema version other than 2 or 3, missing,
            truncated or modified chunk files, columns off-schema, non-contiguous steps, a NaN in a
            path column where none is allowed (``bounce_*`` only for LOS, ``lm_*`` only for OTHER,
            ``power_db`` anywhere), or a transmitter column other than the scenario's BS.

    A version-2 cache loads with the transmitter columns filled from the manifest's BS.
    """
    d = find_cache_dir(path)
    m = read_manifest(d)
    mp = d / MANIFEST
    try:
        scn = scenario_from_resolved(m["resolved_scenario"], source=str(mp))
    except MmslamError as e:
        raise CacheError(f"{mp}: resolved_scenario invalid ({e}); {FORCE_HINT}") from None
    settings_known = isinstance(m.get("settings_defaults"), dict)
    settings_changed: list[str] = []
    if settings_known:  # the parameters its scenario left open follow this mmslam's defaults
        try:
            scn, settings_changed = refresh_settings(m["resolved_scenario"], m.get("scenario_settings"),
                                                     m["settings_defaults"], source=str(mp),
                                                     preset=m.get("scenario") if isinstance(m.get("scenario"), str) else None)
        except MmslamError:  # a recorded table this version reads differently: keep the stored scenario
            settings_known = False
    names = list(m["vehicle_names"])
    n_done = int(m["steps_completed"])
    if n_done == 0:
        raise CacheError(f"{d}: holds no traced step (its trace stopped before the first chunk); re-run mmslam trace "
                         f"on its scenario with the same --out to fill it, or delete {d}")
    how = {"version": int(m["schema_version"]), "bs": scn.bs_array}
    vparts, pparts = [], []
    for c in checked_chunks(m, mp):
        vparts.append(_read_table(d / c["files"]["vehicles"], c["sha256"]["vehicles"], "vehicles", names, **how))
        pparts.append(_read_table(d / c["files"]["paths"], c["sha256"]["paths"], "paths", names, **how))
        for table, part in (("vehicles", vparts[-1]), ("paths", pparts[-1])):
            st = part["step"]
            if st.size and (st.min() < c["step_start"] or st.max() >= c["step_stop"]):
                raise CacheError(f"{d / c['files'][table]}: steps {int(st.min())}..{int(st.max())} outside the "
                                 f"chunk's range {c['step_start']}..{c['step_stop'] - 1}; {FORCE_HINT}")
    veh = _concat(vparts, VEHICLE_COLUMNS)
    paths = sort_paths(_concat(pparts, PATH_COLUMNS))
    nv = len(names)
    if len(veh["step"]) != n_done * nv:
        raise CacheError(f"{mp}: vehicles table has {len(veh['step'])} rows, expected {n_done} steps x "
                         f"{nv} vehicles; {FORCE_HINT}")
    order = np.lexsort((veh["vehicle"], veh["step"]))
    veh = {k: v[order] for k, v in veh.items()}
    grid_ok = (np.array_equal(veh["step"], np.repeat(np.arange(n_done), nv))
               and np.array_equal(veh["vehicle"], np.tile(np.arange(nv), n_done)))
    if not grid_ok:  # right row count, but a (step, vehicle) twice and another missing
        raise CacheError(f"{mp}: vehicles table does not hold each (step, vehicle) exactly once (a duplicated "
                         f"row); {FORCE_HINT}")
    for k in ("t", "x", "y", "z", "heading", "speed", "turn_rate", "vx", "vy", "vz"):
        bad = ~np.isfinite(veh[k])
        if bad.any():
            raise CacheError(f"{d}: vehicles column '{k}' is not finite at step "
                             f"{int(veh['step'][np.argmax(bad)])}; {FORCE_HINT}")
    check_paths_finite(paths, str(d))
    check_paths_physical(paths, str(d))
    states = np.empty((n_done, nv, 7))
    for j, k in enumerate(("x", "y", "z", "heading", "speed", "turn_rate")):
        states[:, :, j] = veh[k].reshape(n_done, nv)
    states[:, :, 6] = np.array([v.initial_state[6] for v in scn.vehicles])[None, :nv]
    scn = dataclasses.replace(scn, steps=max(n_done, 1))
    return PathCache(path=d, manifest=m, scenario=scn, vehicle_names=names, states=states,
                     vehicles=veh, paths=paths, steps=n_done, settings_known=settings_known,
                     settings_changed=tuple(settings_changed))
