"""Filter variants (docs/design.md section 6): one :class:`VariantSpec` per variant, defined once, in a registry.

===========  ===============  =======================================================================
variant      map types        countermeasures
===========  ===============  =======================================================================
odometry     (none updated)   reference: dead reckoning from the prior, no measurement update or fusion
baseline     VA, SP           none (TWC2020; VS paths are unmodelled: false VAs / SPs or clutter)
cm1          VA, SP, VS       local VS map (prediction, birth, correction, its term in ``psi(z)``)
proposed     VA, SP, VS       cm1 + ego-VS averaging, VS prediction at the BS, VS fusion, ego removal
===========  ===============  =======================================================================

The slam run loop, the CLI (``mmslam slam --variant``), the ablation (``--variants``), the report
and the figures read these specs; nothing else compares variant names.
"""
from __future__ import annotations

from dataclasses import dataclass

from mmslam.errors import MmslamError

from .landmarks import LandmarkSpec, landmark_type


@dataclass(frozen=True)
class VariantSpec:
    """One named bundle of filter options.

    Attributes:
        name: the variant's name (CLI, result ``meta['variant']``, ablation labels).
        label: one line for figure legends and the report.
        map_types: names of the landmark types the local filters and the BS map
            (:mod:`mmslam.slam.specs.landmarks`); a type not listed is unmodelled.
        measurement_update: False: dead reckoning (no correction, births, maps or fusion).
        ego_vs_average: the uploaded VS map places the ego vehicle by ``F'_AA`` (eq. 11).
        predict_at_bs: the fused maps of types with a BS predictor are predicted every step (eq. 15).
        vs_fusion: the VS map is fused with the proposed VS fusion (eqs. 16-20) instead of ``F_AA``.
        downlink_ego_removal: on the downlink, VS components matched to the receiving vehicle are
            dropped (when ``fusion.downlink_ego = "remove"``).
        reference: a reference run beside the filter variants (not a filter variant).
    """

    name: str
    label: str
    map_types: tuple[str, ...]
    measurement_update: bool = True
    ego_vs_average: bool = False
    predict_at_bs: bool = False
    vs_fusion: bool = False
    downlink_ego_removal: bool = False
    reference: bool = False

    def describe(self) -> str:
        """One line for the report: its maps and countermeasures, from the flags."""
        if not self.measurement_update:
            return "dead reckoning with the known speed and turn rate (no measurement update, empty maps)"
        cms = [text for on, text in ((self.ego_vs_average, "ego-VS averaging (eq. 11)"),
                                     (self.predict_at_bs, "prediction at the BS (eq. 15)"),
                                     (self.vs_fusion, "VS fusion (eqs. 16-20)"),
                                     (self.downlink_ego_removal, "ego removal on the downlink")) if on]
        return f"maps {', '.join(self.map_types)}; " + (f"countermeasures: {', '.join(cms)}" if cms
                                                        else "AA fusion of every map (eq. 8)")

    def types(self) -> tuple[LandmarkSpec, ...]:
        """The specs of :attr:`map_types`, in order (raises MmslamError for an unknown name)."""
        return tuple(landmark_type(n) for n in self.map_types)


_VARIANTS: dict[str, VariantSpec] = {}


def register_variant(spec: VariantSpec, *, replace: bool = False) -> VariantSpec:
    """Add ``spec`` to the registry; its map types must be registered mapped types. Returns it."""
    if not replace and spec.name in _VARIANTS:
        raise MmslamError(f"variant {spec.name!r} is already registered; pick another name")
    for t in spec.types():
        if not t.mapped:
            raise MmslamError(f"variant {spec.name!r}: {t.name} is a known landmark, not a map type")
    _VARIANTS[spec.name] = spec
    return spec


def unregister_variant(name: str) -> None:
    """Remove a registered variant (tests; the built-in ones stay)."""
    if name in BUILTIN_VARIANTS:
        raise MmslamError(f"variant {name!r} is built in and cannot be removed")
    _VARIANTS.pop(name, None)


def variant_names(reference: bool | None = None) -> tuple[str, ...]:
    """Registered variant names in registration order; ``reference``: only references (True) /
    only filter variants (False) / all (None)."""
    return tuple(n for n, v in _VARIANTS.items() if reference is None or v.reference == reference)


def get_variant(variant: str | VariantSpec) -> VariantSpec:
    """The spec of a variant name (a spec is returned as is).

    Raises:
        MmslamError: unknown variant (naming the known ones).
    """
    if isinstance(variant, VariantSpec):
        return variant
    spec = _VARIANTS.get(str(variant))
    if spec is None:
        raise MmslamError(f"unknown variant {variant!r}; expected one of {', '.join(_VARIANTS)}")
    return spec


for _v in (
    VariantSpec("odometry", "odometry (dead reckoning, empty map)", ("VA", "SP"), measurement_update=False,
                reference=True),
    VariantSpec("baseline", "baseline (TWC2020)", ("VA", "SP")),
    VariantSpec("cm1", "countermeasure 1", ("VA", "SP", "VS")),
    VariantSpec("proposed", "proposed (both countermeasures)", ("VA", "SP", "VS"), ego_vs_average=True,
                predict_at_bs=True, vs_fusion=True, downlink_ego_removal=True),
):
    register_variant(_v)
DEFAULT_VARIANT = "proposed"
"""The variant of a run that names none (`mmslam slam`, :func:`~mmslam.slam.filter.run.run_slam`,
:func:`~mmslam.slam.filter.run.run_filter`): the paper's filter, the one every figure of docs/city-slam.md is measured
with. ``baseline`` (TWC2020) does not model the other cars: in a city their paths become false VAs (docs/city-slam.md,
"The default variant")."""
COMPARED_WITH = "baseline"
"""The variant every other one is compared with (paired differences in the ablation summary and report)."""
BUILTIN_VARIANTS: tuple[str, ...] = tuple(_VARIANTS)
"""The built-in variants, in plotting order: the reference first."""
VARIANTS: tuple[str, ...] = variant_names(reference=False)
"""The built-in filter variants (``baseline, cm1, proposed``)."""
REFERENCES: tuple[str, ...] = variant_names(reference=True)
"""The built-in reference runs (``odometry``: dead reckoning from the prior with the known speed
and turn rate, no measurement update and empty maps; its map GOSPA is that of an empty map)."""
