"""Parameters declared once: default, doc, unit and bounds on the dataclass field itself.

Every tunable parameter of a scenario section (``[sensor]``, ``[filter]``, ``[fusion]``,
``[evaluation]``) is a dataclass field made by :func:`param`. Its metadata drives the TOML
validation (:func:`check_value`), the generated scenario reference (:func:`param_rows`) and
``--set section.key=value`` overrides (:func:`parse_override`), so a parameter is written down in
exactly one place.

Bounds are inclusive unless ``lo_open`` / ``hi_open``; for vectors they apply to every element.
"""
from __future__ import annotations

import dataclasses
import math
import tomllib
from dataclasses import dataclass
from typing import Any, Iterator

_META = "mmslam.param"


@dataclass(frozen=True)
class ParamSpec:
    """What is declared about one parameter (stored in the field's metadata)."""

    doc: str
    unit: str = ""
    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False
    hi_open: bool = False
    choices: tuple[str, ...] | None = None
    integer: bool = False
    length: int | None = None
    """Vector parameters: required length (``None``: any non-empty length)."""
    probability: bool = False
    """A probability (bounds [0, 1])."""

    def bounds_text(self) -> str:
        if self.choices is not None:
            return " | ".join(self.choices)
        lo = "" if self.lo is None else f"{'(' if self.lo_open else '['}{_num_text(self.lo)}"
        hi = "" if self.hi is None else f"{_num_text(self.hi)}{')' if self.hi_open else ']'}"
        if not lo and not hi:
            return "any"
        return f"{lo or '(-inf'}, {hi or 'inf)'}"


def _num_text(x: float) -> str:
    """A bound as text: exact for integers below 1e12 (2**32 - 1, not 4.29497e+09), else ``:g``."""
    return str(int(x)) if float(x).is_integer() and abs(x) < 1e12 and (abs(x) < 1e5 or x % 1000 != 0) else f"{x:g}"


def param(default: Any, doc: str, unit: str = "", *, lo: float | None = None, hi: float | None = None,
          lo_open: bool = False, hi_open: bool = False, choices: tuple[str, ...] | None = None,
          length: int | None = None, probability: bool = False) -> Any:
    """A dataclass field with its :class:`ParamSpec` (``default`` may be a tuple for vectors).

    ``probability=True`` declares bounds [0, 1]."""
    if probability:
        lo, hi = 0.0, 1.0
    integer = isinstance(default, int) and not isinstance(default, bool)
    if isinstance(default, tuple) and default and all(isinstance(x, int) for x in default):
        integer = True
    spec = ParamSpec(doc, unit, lo, hi, lo_open, hi_open, choices, integer, length, probability)
    return dataclasses.field(default=default, metadata={_META: spec})


def spec_of(f: dataclasses.Field) -> ParamSpec | None:
    return f.metadata.get(_META)


def iter_params(cls: type) -> Iterator[tuple[dataclasses.Field, ParamSpec]]:
    """``(field, spec)`` of each declared parameter of dataclass ``cls``, in declaration order."""
    for f in dataclasses.fields(cls):
        s = spec_of(f)
        if s is not None:
            yield f, s


def _check_scalar(key: str, v: Any, spec: ParamSpec, kind: type) -> Any:
    """One scalar against ``spec``; returns the converted value or raises ``ValueError(message)``."""
    if kind is bool:
        if not isinstance(v, bool):
            raise ValueError(f"expected true or false, got {v!r}")
        return v
    if kind is str:
        if not isinstance(v, str):
            raise ValueError(f"expected a string, got {v!r}")
        if spec.choices is not None and v not in spec.choices:
            raise ValueError(f"expected one of {list(spec.choices)}, got {v!r}")
        return v
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise ValueError(f"expected a {'integer' if spec.integer else 'number'}, got {v!r}")
    if not math.isfinite(float(v)):
        raise ValueError(f"expected a finite number, got {v!r}")
    if spec.integer and not float(v).is_integer():
        raise ValueError(f"expected an integer, got {v!r}")
    lo_bad = spec.lo is not None and (v < spec.lo or (spec.lo_open and v == spec.lo))
    hi_bad = spec.hi is not None and (v > spec.hi or (spec.hi_open and v == spec.hi))
    if (lo_bad or hi_bad) and spec.probability:
        raise ValueError(f"expected a probability in [0, 1], got {v!r}")
    if lo_bad or hi_bad:
        raise ValueError(f"expected a value in {spec.bounds_text()}{' ' + spec.unit if spec.unit else ''}, "
                         f"got {v!r}")
    return int(v) if spec.integer else float(v)


def check_value(f: dataclasses.Field, v: Any) -> Any:
    """Validate and convert TOML value ``v`` for field ``f``; raises ``ValueError(message)``."""
    spec = spec_of(f)
    assert spec is not None, f.name
    default = f.default
    if isinstance(default, tuple):
        if not isinstance(v, list) or not v or (spec.length is not None and len(v) != spec.length):
            n = f"a list of {spec.length} " if spec.length is not None else "a non-empty list of "
            raise ValueError(f"expected {n}{'integers' if spec.integer else 'numbers'}, got {v!r}")
        out = []
        for i, x in enumerate(v):
            try:
                out.append(_check_scalar(f.name, x, spec, float))
            except ValueError as e:
                raise ValueError(f"element {i}: {e}") from None
        return tuple(out)
    kind = bool if isinstance(default, bool) else str if isinstance(default, str) else float
    return _check_scalar(f.name, v, spec, kind)


def did_you_mean(name: str, known: list[str] | set[str]) -> str | None:
    """The known name closest to a mistyped ``name`` (``difflib``, similarity at least 0.75), or None."""
    import difflib

    close = difflib.get_close_matches(name, sorted(known), n=1, cutoff=0.75)
    return close[0] if close else None


def parse_override(text: str) -> tuple[str, Any]:
    """``"section.key=value"`` -> ``("section.key", value)``; the value is read as TOML
    (``4``, ``0.5``, ``true``, ``[1, 2]``, ``"all"``); a bare word is taken as a string."""
    if "=" not in text:
        raise ValueError(f"--set {text!r}: expected section.key=value (e.g. filter.merge=4)")
    key, raw = (s.strip() for s in text.split("=", 1))
    if not key or not raw:
        raise ValueError(f"--set {text!r}: expected section.key=value (e.g. filter.merge=4)")
    try:
        value = tomllib.loads(f"v = {raw}")["v"]
    except tomllib.TOMLDecodeError:
        value = raw
    except RecursionError:  # e.g. thousands of nested [ ]: tomllib recurses per level
        raise ValueError(f"--set {key}: the value is nested too deeply; give a number, a word or a flat "
                         "list") from None
    return key, value


def param_rows(cls: type, section: str) -> list[tuple[str, str, str, str, str]]:
    """``(key, default, unit, bounds, doc)`` rows for the scenario reference."""
    rows = []
    for f, s in iter_params(cls):
        d = f.default
        dtext = "[" + ", ".join(f"{x:g}" if isinstance(x, float) else str(x) for x in d) + "]" \
            if isinstance(d, tuple) else ("not set" if d is None else str(d).lower() if isinstance(d, bool) else
                                           f'"{d}"' if isinstance(d, str) else f"{d:g}")
        rows.append((f"{section}.{f.name}", dtext, s.unit or "-", s.bounds_text(), s.doc))
    return rows
