"""Landmark types of the filter: one :class:`LandmarkSpec` per type, defined once, in a registry.

Everything the filter, the sensor model, the fusion centre and the evaluation need to know about
a landmark type lives in its spec (nothing else in ``slam/`` compares type codes):

============  =====  ==========  =====  =============  ==========  ================================
type          code   geometry    dim    FOV gate       dynamics    fusion operator
============  =====  ==========  =====  =============  ==========  ================================
BS (known)    0      DIRECT      3      none           --          -- (a known landmark, no map)
VA            1      MIRROR      3      none           static      AA fusion ``F_AA`` (eq. 8)
SP            2      SCATTER     3      fov_range      static      AA fusion ``F_AA`` (eq. 8)
VS            3      SCATTER     7      fov_range      CT (eq. 2)  ``F_AA`` (cm1), or ego average
                                                                   (eq. 11), VS fusion (eqs. 16-20)
============  =====  ==========  =====  =============  ==========  ================================

- **geometry** (:class:`~mmslam.model.Bounce`): how a landmark point maps to a measurement
  (eq. 3) and how a measurement is inverted to a birth point (the MIRROR / SCATTER inversions of
  :mod:`mmslam.slam.phd.birth`); the kernels take this geometry code.
- **FOV gate**: a landmark of a range-gated type is detectable only within ``sensor.fov_range``
  of the vehicle (the sensor model, the filter's ``p_D`` and the accumulated FOV at fusion use
  :meth:`LandmarkSpec.fov_radius`); the others are always in the FOV (infinite radius).
- **dynamics**: the local prediction of the type's map (:data:`predict_static_map`: survival
  ``p_S``; :func:`predict_vs_map`: coordinated turn with dithering), and optionally a prediction
  at the BS between uploads (:func:`predict_vs_at_bs`, variant flag ``predict_at_bs``).
- **parameters**: its row of the per-type table ``[filter.types.<NAME>]`` (detection probability
  ``p_detect``, estimate threshold ``threshold``, merge gate ``merge``;
  :class:`mmslam.scenes.scenario.TypeParams`), or the row named by ``params``.
- **evaluation**: ``moving`` types (VS) against the other vehicles' true positions, static ones the landmarks seen.

Adding a type (docs/extending.md): make a :class:`LandmarkSpec` with its functions and
:func:`register_landmark_type` it; a :class:`~mmslam.slam.specs.variants.VariantSpec` naming it in
``map_types`` runs it.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable

import numpy as np

from mmslam.errors import ConfigError, MmslamError
from mmslam.model import OTHER, Bounce, LandmarkType, set_landmark_type_name, unknown_type_row

from ..models.dynamics import predict_static
from ..phd.birth import birth_from_moments
from ..core.gm import NO_LABEL, GM, concat, concat_label, concat_pd_beta, ego_label
from ..phd.reduction import merge_pairs, prune_merge
from .vehicle_body import vs_birth_moments, vs_body, vs_on_road

if TYPE_CHECKING:  # pragma: no cover
    from mmslam.scenes.scenario import Scenario, SensorParams, TypeParams

    from .variants import VariantSpec

PdFn = Callable[[np.ndarray, np.ndarray, int], np.ndarray]
"""``pd_fn(vehicle_pos (..., 3), lm_pos (..., 3), lm_type code) -> (...)`` detection probability."""


def point_extent(scn: "Scenario") -> None:
    """A point landmark: the measured point is the landmark state's position (no extent)."""
    return None


def point_body(scn: "Scenario") -> None:
    """A point landmark: a path bounces at the landmark state's position (no body)."""
    return None


@dataclass(frozen=True)
class FusionInput:
    """What a type's fusion operator gets besides the two maps (one vehicle's upload at the BS).

    ``ego_mean (7,)``, ``ego_cov (7, 7)``: the uploading vehicle's state posterior; ``vehicle``: its
    index (the label of its ego Gaussian, :func:`mmslam.slam.core.gm.ego_label`), or None (no label).
    """

    scn: "Scenario"
    variant: "VariantSpec"
    ego_mean: np.ndarray
    ego_cov: np.ndarray
    vehicle: int | None = None


FuseFn = Callable[[GM, GM, np.ndarray, FusionInput], "tuple[GM, np.ndarray | None]"]
"""``fuse(bs_map, upload, inside (n_bs,), FusionInput) -> (fused union, matched pairs or None)``."""


@dataclass(frozen=True)
class LandmarkSpec:
    """One landmark type of the filter (see the module docstring for the built-in ones).

    Attributes:
        name: short name (``"VA"``); result tables and parameter names use it.
        code: integer code in path caches (``paths.type``) and measurement origins.
        geometry: path geometry (:class:`~mmslam.model.Bounce`) of ``h(s, x)`` and of the birth
            inversion.
        state_dim: dimension of the map state (position first: ``[x, y, z, ...]``).
        description: one line for figures and reports.
        range_gated: detectable only within ``sensor.fov_range`` (m) of the vehicle.
        mapped: the filter keeps a map of it (False: a known landmark, the BS).
        moving: scored against the vehicles' true positions (else: static first-seen truth).
        params: the row of the per-type table ``[filter.types.<row>]`` with its detection
            probability inside the FOV, estimate threshold and merge gate ``U`` ('' = its own ``name``;
            a type without a row gets :class:`~mmslam.scenes.scenario.TypeParams`'s defaults).
        learns_pd: with ``filter.pd_model = "beta"`` its Gaussians carry a Beta of their own
            detection probability (:mod:`mmslam.slam.phd.detection`; VA and SP, not the moving VS).
        predict: ``predict(map, births or None, scn) -> map``, the local prediction from k-1 to k
            (births are added to the predicted map).
        birth: ``birth(states (P, 7), moments, spec, scn, pd_fn, unexplained, new) -> GM`` (:func:`birth_point`), ``moments``
            = ``(mean (P, J, 3), cov (P, J, 3, 3), ok (P, J))`` of the geometry's inversion.
        extent: ``extent(scn) -> (3, 3) or None``, covariance of the measured point about the
            landmark state's position (None: a point).
        body: ``body(scn) -> (4,) or None``, the body ``[length, width, height, depth]`` (m) at whose
            specular point a path bounces (:func:`mmslam.slam.models.vs.body_specular_point`; None: a point).
        survive: ``survive(predicted map, states (P, 7), scn) -> map``: the Gaussians the type's model rules
            out after a local prediction removed (VS: :func:`vs_on_road`), or None.
        fuse: ``fuse(bs_map, upload, inside (n_bs,), FusionInput) -> (fused, matched pairs)``, the
            type's fusion operator (:data:`FuseFn`).
        fuse_for: ``fuse_for(variant) -> FuseFn``: the operator a variant uses, chosen when the
            variant's fusion centre is built (:meth:`fusion_operator`); None: ``fuse`` for every variant.
        reduce_fused: ``reduce_fused(fused, pairs, scn, spec) -> GM``, the reduction after fusion (``spec``:
            this type's spec, e.g. for its :meth:`merge_gate`).
        predict_at_bs: ``predict_at_bs(fused map, scn) -> map`` between uploads (only for variants
            with ``predict_at_bs``), or None.
        remove_ego: ``remove_ego(fused map, (mean (7,), cov (7, 7)), scn) -> map`` on the downlink
            (variants with ``downlink_ego_removal``), or None.
    """

    name: str
    code: int
    geometry: Bounce
    state_dim: int
    description: str
    range_gated: bool
    mapped: bool = True
    moving: bool = False
    params: str = ""
    learns_pd: bool = False
    predict: Callable[[GM, GM | None, "Scenario"], GM] | None = None
    birth: Callable[..., GM] | None = None
    extent: Callable[["Scenario"], np.ndarray | None] = point_extent
    body: Callable[["Scenario"], np.ndarray | None] = point_body
    survive: Callable[[GM, np.ndarray, "Scenario"], GM] | None = None
    fuse: FuseFn | None = None
    fuse_for: Callable[["VariantSpec"], FuseFn] | None = None
    reduce_fused: Callable[[GM, np.ndarray | None, "Scenario", "LandmarkSpec"], GM] | None = None
    predict_at_bs: Callable[[GM, "Scenario"], GM] | None = None
    remove_ego: Callable[[GM, tuple[np.ndarray, np.ndarray], "Scenario"], GM] | None = None

    def __post_init__(self) -> None:
        if not self.params:
            object.__setattr__(self, "params", self.name)

    def type_params(self, scn: "Scenario") -> "TypeParams":
        """This type's row of ``filter.types`` (:class:`~mmslam.scenes.scenario.TypeParams`)."""
        return scn.filter.type_params(self.params)

    def fov_radius(self, sensor: "SensorParams") -> float:
        """Radius (m) of the FOV about the vehicle: ``sensor.fov_range`` if range-gated, else infinite."""
        return float(sensor.fov_range) if self.range_gated else float("inf")

    def p_detect(self, scn: "Scenario") -> float:
        """The filter's detection probability inside the FOV (``filter.types.<params>.p_detect``)."""
        return float(self.type_params(scn).p_detect)

    def pd_beta_prior(self, scn: "Scenario") -> tuple[float, float] | None:
        """Birth Beta ``(s0, t0)`` of this type's detection probability (mean ``filter.types.<params>.p_detect``,
        pseudo-count ``filter.pd_beta_count``), or None where the type's ``p_D`` is fixed
        (``filter.pd_model = "fixed"``, or a type that does not ``learns_pd``)."""
        if scn.filter.pd_model != "beta" or not self.learns_pd:
            return None
        from ..phd.detection import prior_beta

        return prior_beta(self.p_detect(scn), float(scn.filter.pd_beta_count))

    def fusion_operator(self, variant: "VariantSpec") -> FuseFn:
        """The fusion operator of this type for ``variant`` (``fuse_for(variant)``, else ``fuse``)."""
        return self.fuse if self.fuse_for is None else self.fuse_for(variant)

    def merge_gate(self, scn: "Scenario") -> float:
        """Merge gate ``U`` (squared Mahalanobis distance, dimensionless) of this type's maps
        (``filter.types.<params>.merge``; not set: ``filter.merge``)."""
        return self.type_params(scn).merge_gate(scn.filter.merge)

    def threshold(self, scn: "Scenario") -> float:
        """Estimate threshold on a component's weight (``filter.types.<params>.threshold``)."""
        if not self.mapped:
            raise MmslamError(f"landmark type {self.name!r} is not mapped and has no estimate threshold")
        return float(self.type_params(scn).threshold)


# ====================================================================== the types' functions
def predict_static_map(g: GM, born: GM | None, scn: "Scenario") -> GM:
    """Static landmarks: weights times ``p_S`` (eq. 4; a Beta detection history fades by
    ``filter.pd_beta_forget``, :func:`mmslam.slam.phd.detection.predict_beta`), then the births appended."""
    g = predict_static(g, scn.filter.p_survival)
    if g.pd_beta is not None:
        from ..phd.detection import predict_beta

        g.pd_beta = predict_beta(g.pd_beta, float(scn.filter.pd_beta_forget))
    return g if born is None else concat(g, born)


def predict_vs_map(g: GM, born: GM | None, scn: "Scenario") -> GM:
    """VS map: coordinated turn (eq. 2 / 9) with process noise ``filter.vs_process_std``; dithering
    ``filter.vs_dither`` on every Gaussian (scope ``all``) or on the births only (``newborn``). The
    predicted map and its predicted births are written side by side into one mixture."""
    from ..models.vs import predict_vs_into, process_noise

    fp = scn.filter
    if born is None or not born.capacity:
        born = None
        if not g.capacity:
            return g
    q, dither = np.asarray(fp.vs_process_std), np.asarray(fp.vs_dither)
    add_old = process_noise(q, dither if fp.vs_dither_scope == "all" else None)
    qa, qb = g.capacity, 0 if born is None else born.capacity
    shape = g.batch_shape + (qa + qb,)
    out = GM(np.empty(shape), np.empty(shape + (g.dim,)), np.empty(shape + (g.dim, g.dim)), np.empty(shape, bool),
             g.pd_beta if born is None else concat_pd_beta(g, born),
             g.label if born is None else concat_label(g, born))
    if qa:
        predict_vs_into(g, scn.dt, fp.p_survival, add_old, out, 0)
    if born is not None:
        predict_vs_into(born, scn.dt, fp.p_survival, process_noise(q, dither), out, qa)
    return out


def birth_point(states: np.ndarray, moments: tuple[np.ndarray, np.ndarray, np.ndarray], spec: LandmarkSpec,
                scn: "Scenario", pd_fn: PdFn, unexplained: np.ndarray | None = None, new: np.ndarray | None = None) -> GM:
    """Birth Gaussians (weight ``filter.birth_weight``) at the inverted points of the previous step's measurements, one
    slot per measurement with a birth in some particle (:func:`mmslam.slam.phd.birth.birth_from_moments`; a 7-D VS birth:
    velocity / turn-rate prior ``filter.vs_birth_velocity_var``, ``vs_birth_turn_std``), the type's Beta detection prior
    where it has one. ``new (P, J)`` bool: the births that are new landmarks by their own measurement (``first_detection``)
    weigh the type's ``birth_existence`` instead; ``unexplained (P, J)`` (``filter.adaptive_birth``): times it."""
    fp = scn.filter
    weight = (fp.birth_weight if new is None else np.where(new, spec.type_params(scn).birth_existence, fp.birth_weight)
              ) * (1.0 if unexplained is None else np.asarray(unexplained, float))
    born = birth_from_moments(states, *moments, spec, weight, pd_fn, fp.vs_birth_velocity_var, fp.vs_birth_turn_std,
                              drop_dead=True)
    prior = spec.pd_beta_prior(scn)
    if prior is not None:
        born.pd_beta = np.broadcast_to(np.asarray(prior, float), born.w.shape + (2,)).copy()
    return born


def birth_vs(states: np.ndarray, moments: tuple[np.ndarray, np.ndarray, np.ndarray], spec: LandmarkSpec,
             scn: "Scenario", pd_fn: PdFn, unexplained: np.ndarray | None = None, new: np.ndarray | None = None) -> GM:
    """:func:`birth_point` of a VS from :func:`~mmslam.slam.specs.vehicle_body.vs_birth_moments` (road band only)."""
    return birth_point(states, vs_birth_moments(states, moments, scn), spec, scn, pd_fn, unexplained, new)


def vs_extent(scn: "Scenario") -> np.ndarray | None:
    """``(3, 3)`` covariance of a VS bounce point about the car's antenna (``filter.vs_extent_std``), None if 0."""
    h, v = (float(x) for x in scn.filter.vs_extent_std)
    return np.diag([h * h, h * h, v * v]) if (h or v) else None


def fuse_aa(bs_map: GM, upload: GM, inside: np.ndarray, ctx: FusionInput) -> tuple[GM, np.ndarray | None]:
    """AA fusion ``F_AA`` (eq. 8, TWC2020): MSM matching with ``fusion.msm_position``, matched pairs
    weighted by ``fusion.aa_weights`` (``visibility``: by each member's learnt ``E[p_D]``)."""
    from ..fusion import operators as fm

    fu = ctx.scn.fusion
    return fm.fuse_aa(bs_map, upload, inside, fu.msm_position, with_pairs=True, weights=fu.aa_weights)


def fuse_vs(bs_map: GM, upload: GM, inside: np.ndarray, ctx: FusionInput) -> tuple[GM, np.ndarray | None]:
    """The proposed VS fusion ``F'_AA`` of the BS and uploaded VS maps (eqs. 16-20; gates
    ``fusion.msm_position`` / ``msm_velocity``, ``fusion.beta_inside_fov`` for unmatched BS components)."""
    from ..fusion import operators as fm

    fu = ctx.scn.fusion
    return fm.fuse_vs(bs_map, upload, inside, fu.msm_position, fu.msm_velocity, fu.beta_inside_fov, with_pairs=True)


def ego_averaged(upload: GM, ctx: FusionInput) -> GM:
    """The uploaded VS map with the ego vehicle placed by ``F'_AA`` (eq. 11): its ego Gaussian
    (:func:`mmslam.slam.fusion.operators.ego_gaussian`: the car's antenna position, the VS state),
    labelled with the vehicle's ego label. The body's scatter extent :func:`vs_extent` is not added
    here: it enters once, in every vehicle's VS likelihood (``ckf.ckf_update``)."""
    from ..fusion import operators as fm

    scn = ctx.scn
    em, ec = fm.ego_gaussian(ctx.ego_mean, ctx.ego_cov, scn.filter.vs_process_std)
    return fm.ego_vs_average(upload, em, ec, scn.fusion.msm_position,
                             NO_LABEL if ctx.vehicle is None else ego_label(ctx.vehicle))


def vs_fusion_operator(variant: "VariantSpec") -> FuseFn:
    """The VS map's fusion operator of a variant, chosen once when its fusion centre is built:
    ``vs_fusion``: :func:`fuse_vs` (eqs. 16-20), else :func:`fuse_aa` (eq. 8); ``ego_vs_average``:
    applied to the :func:`ego_averaged` upload (eq. 11)."""
    fuse = fuse_vs if variant.vs_fusion else fuse_aa
    if not variant.ego_vs_average:
        return fuse

    def fuse_ego_averaged(bs_map: GM, upload: GM, inside: np.ndarray, ctx: FusionInput) -> tuple[GM, np.ndarray | None]:
        return fuse(bs_map, ego_averaged(upload, ctx), inside, ctx)

    return fuse_ego_averaged


def trace_cap(spec: LandmarkSpec, scn: "Scenario") -> float | None:
    """The position-trace cap (m^2) of ``spec``'s maps: ``filter.max_trace`` for a moving type (its Gaussians grow by
    process noise), None (no cap) for a static one unless ``filter.max_trace_scope = "all"``. A static Gaussian's
    covariance only shrinks after its birth, whose covariance is what one measurement resolves (``r_scale R`` mapped
    to position at the landmark's range): an absolute cap then only drops births, all of them once the noise grows
    (2x the `paper` noise: every VA birth above 50 m^2, no VA mapped)."""
    fp = scn.filter
    return float(fp.max_trace) if spec.moving or fp.max_trace_scope == "all" else None


def reduce_fused_static(fused: GM, pairs: np.ndarray | None, scn: "Scenario", spec: LandmarkSpec) -> GM:
    """``prune_merge`` of a fused map (``fusion.average_prune``, :meth:`LandmarkSpec.merge_gate`, :func:`trace_cap`).
    Where the fusion weighted its matched ``pairs (n, 2)`` by visibility (``aa_weights = "visibility"``, a Beta on both
    maps) each pair is one landmark, merged first whatever the gate: it keeps ``beta_b w_b + beta_u w_u`` (city-slam.md,
    "The fusion's lost share"). With equal shares (the paper's eq. (8)) the union is reduced as published."""
    fp, fu = scn.filter, scn.fusion
    if fused.capacity and pairs is not None and len(pairs) and fu.aa_weights == "visibility" and fused.pd_beta is not None:
        fused = merge_pairs(fused, pairs)
    if fused.capacity:
        fused = prune_merge(fused, fu.average_prune, spec.merge_gate(scn), fp.max_gaussians, trace_cap(spec, scn),
                            pos_dims=3)
    return fused


def reduce_fused_vs(fused: GM, pairs: np.ndarray | None, scn: "Scenario", spec: LandmarkSpec | None = None) -> GM:
    """``fusion.vs_reduction``: merge the matched pairs only (``matched``), or every pair within
    ``fusion.vs_merge_gate`` (``gate``); then prune / cap."""
    fp, fu = scn.filter, scn.fusion
    if fu.vs_reduction == "matched":
        fused, gate = merge_pairs(fused, pairs), 0.0
    else:
        gate = fu.vs_merge_gate
    if fused.capacity:
        fused = prune_merge(fused, fu.average_prune, gate, fp.max_gaussians, fp.max_trace, pos_dims=3)
    return fused


def predict_vs_at_bs(g: GM, scn: "Scenario") -> GM:
    """The fused VS map predicted one step at the BS without birth (eq. 15)."""
    from ..fusion.operators import predict_bs_vs

    fp = scn.filter
    return predict_bs_vs(g, scn.dt, fp.p_survival, np.asarray(fp.vs_process_std), 1)


def remove_ego_vs(g: GM, ego: tuple[np.ndarray, np.ndarray], scn: "Scenario") -> GM:
    """Drop the fused VS components matched to the receiving vehicle itself (``fusion.downlink_ego``
    = ``remove``; the vehicle is no scatterer of its own map)."""
    from ..fusion.operators import remove_ego

    if scn.fusion.downlink_ego != "remove":
        return g
    return remove_ego(g, ego[0], ego[1], scn.fusion.msm_position)


# ====================================================================== registry
_REGISTRY: dict[str, LandmarkSpec] = {}
_CODES: dict[int, LandmarkSpec] = {}
"""code -> spec, kept in step with the registry."""


def register_landmark_type(spec: LandmarkSpec, *, replace: bool = False) -> LandmarkSpec:
    """Add ``spec`` to the registry (by name; its code must be new too). Returns it.

    Raises:
        MmslamError: the name or code is taken (unless ``replace``), the code is ``OTHER`` or not an
            integer, the geometry is not a :class:`~mmslam.model.Bounce`, or a mapped type has a DIRECT
            geometry, fewer than 3 state components or lacks its functions.
    """
    if not replace and spec.name in _REGISTRY:
        raise MmslamError(f"landmark type {spec.name!r} is already registered; pick another name")
    taken = {c: s.name for c, s in _CODES.items() if s.name != spec.name}
    if spec.code in taken or spec.code == OTHER or spec.code < 0:
        raise MmslamError(f"landmark type {spec.name!r}: code {spec.code} is taken "
                          f"({taken.get(spec.code, 'OTHER')}); pick an unused code >= 0")
    if not isinstance(spec.code, (int, np.integer)) or isinstance(spec.code, bool):
        raise MmslamError(f"landmark type {spec.name!r}: code {spec.code!r} must be an integer")
    try:
        geometry = Bounce(spec.geometry)
    except ValueError:
        raise MmslamError(f"landmark type {spec.name!r}: geometry {spec.geometry!r} is not a path geometry; "
                          f"use one of {', '.join(b.name for b in Bounce)} (mmslam.model.Bounce)") from None
    if spec.mapped and (geometry == Bounce.DIRECT or spec.state_dim < 3):
        raise MmslamError(f"landmark type {spec.name!r}: a mapped type needs a MIRROR or SCATTER geometry and "
                          f"a state of at least 3 components (position first), got {geometry.name}, "
                          f"state_dim {spec.state_dim}")
    if spec.mapped and None in (spec.predict, spec.birth, spec.fuse, spec.reduce_fused):
        raise MmslamError(f"landmark type {spec.name!r}: a mapped type needs predict, birth, fuse and reduce_fused")
    _REGISTRY[spec.name] = spec
    set_landmark_type_name(spec.name, True)
    _CODES.clear()
    _CODES.update({s.code: s for s in _REGISTRY.values()})
    return spec


def unregister_landmark_type(name: str) -> None:
    """Remove a registered type (tests; the built-in types stay)."""
    if name in BUILTIN_TYPES:
        raise MmslamError(f"landmark type {name!r} is built in and cannot be removed")
    _REGISTRY.pop(name, None)
    set_landmark_type_name(name, False)
    _CODES.clear()
    _CODES.update({s.code: s for s in _REGISTRY.values()})


def check_type_rows(scn: "Scenario") -> None:
    """Every ``[filter.types.<TYPE>]`` row of ``scn`` (from a file, ``--set`` or ``--grid``) names a registered
    type: a misspelt row (``filter.types.sp``) would otherwise set nothing, silently; and no moving type's row sets a
    random walk (``drift_std``), a follow offset (``follow_std``) or a weight offset (``weight_std``), whatever the
    variant maps. One-line ConfigError.
    (The scenario loader refuses an unknown row already; this guards a Scenario built in code.)"""
    unknown = sorted(set(scn.filter.types) - set(_REGISTRY))
    if unknown:
        raise ConfigError(f"filter.types.{unknown[0]}: {unknown_type_row(unknown[0])}")
    for spec in _REGISTRY.values():  # a moving type's motion noise is its own: no random walk on top
        for key in ("drift_std", "follow_std"):
            if spec.moving and spec.mapped and getattr(spec.type_params(scn), key) > 0:
                raise ConfigError(f"filter.types.{spec.params}.{key}: a moving type's motion noise is its own "
                                  f"(filter.vs_process_std); set {key} = 0")
        if spec.moving and spec.mapped and spec.type_params(scn).weight_std > 0:
            raise ConfigError(f"filter.types.{spec.params}.weight_std: a moving type's likelihood has its own body "
                              "model (filter.vs_body_model); set weight_std = 0")


def landmark_types() -> tuple[LandmarkSpec, ...]:
    """All registered types, in registration order (BS, VA, SP, VS, then any added ones)."""
    return tuple(_REGISTRY.values())


def landmark_type(name_or_code: str | int) -> LandmarkSpec:
    """The spec of a type by name (``"VS"``) or code (``3``).

    Raises:
        MmslamError: no such type.
    """
    if isinstance(name_or_code, str):
        spec = _REGISTRY.get(name_or_code)
    else:
        spec = _CODES.get(int(name_or_code))
    if spec is None:
        known = ", ".join(f"{s.name}={s.code}" for s in _REGISTRY.values())
        raise MmslamError(f"unknown landmark type {name_or_code!r}; expected one of {known}")
    return spec


def geometry_of(name_or_code: str | int) -> int:
    """The path geometry (:class:`~mmslam.model.Bounce` code) of a registered type (name or code);
    MmslamError for an unknown type. Building blocks are handed this (or the spec), never the code."""
    return int(landmark_type(name_or_code).geometry)


def mapped_types() -> tuple[LandmarkSpec, ...]:
    """Registered types the filter maps (all but the known BS)."""
    return tuple(s for s in _REGISTRY.values() if s.mapped)


def range_gated_codes() -> np.ndarray:
    """``(n,)`` codes of the range-gated types (SP, VS, ...)."""
    return np.array([s.code for s in _REGISTRY.values() if s.range_gated], dtype=int)


def is_range_gated(codes: int | np.ndarray) -> np.bool_ | np.ndarray:
    """Whether landmarks of these type codes are gated by ``sensor.fov_range`` (unknown codes: no);
    a NumPy bool (``~`` negates it) or a bool array of the shape of ``codes``."""
    if isinstance(codes, (int, np.integer)) or np.ndim(codes) == 0:  # isinstance first: np.ndim takes ~2 us
        spec = _CODES.get(int(codes))
        return np.bool_(spec is not None and spec.range_gated)
    return np.isin(np.asarray(codes), range_gated_codes())


def known_codes() -> tuple[int, ...]:
    """Codes a path may carry: the registered types and ``OTHER``."""
    return tuple(sorted({s.code for s in _REGISTRY.values()} | {OTHER}))


BS_SPEC = LandmarkSpec(
    name="BS", code=int(LandmarkType.BS), geometry=Bounce.DIRECT, state_dim=3, mapped=False, range_gated=False,
    description="base station (line of sight, a known landmark)")
"""The BS: a known landmark (no map, no estimates); its detection probability is ``filter.p_detect_bs``."""
VA_SPEC = LandmarkSpec(
    name="VA", code=int(LandmarkType.VA), geometry=Bounce.MIRROR, state_dim=3, range_gated=False,
    description="virtual anchor (VA)", predict=predict_static_map, birth=birth_point, fuse=fuse_aa,
    reduce_fused=reduce_fused_static, learns_pd=True)
SP_SPEC = LandmarkSpec(
    name="SP", code=int(LandmarkType.SP), geometry=Bounce.SCATTER, state_dim=3, range_gated=True,
    description="scattering point (SP)", predict=predict_static_map, birth=birth_point, fuse=fuse_aa,
    reduce_fused=reduce_fused_static, learns_pd=True)
VS_SPEC = LandmarkSpec(
    name="VS", code=int(LandmarkType.VS), geometry=Bounce.SCATTER, state_dim=7, range_gated=True, moving=True,
    description="vehicle scatterer (VS)", predict=predict_vs_map, birth=birth_vs, extent=vs_extent, body=vs_body, survive=vs_on_road,
    fuse=fuse_aa, fuse_for=vs_fusion_operator, reduce_fused=reduce_fused_vs, predict_at_bs=predict_vs_at_bs,
    remove_ego=remove_ego_vs)

for _s in (BS_SPEC, VA_SPEC, SP_SPEC, VS_SPEC):
    register_landmark_type(_s)
BUILTIN_TYPES: tuple[str, ...] = tuple(_REGISTRY)
"""Names of the built-in types (``BS, VA, SP, VS``)."""
