"""The fusion centre at the BS: fused maps per landmark type and the variants' fusion rules (paper III-B, IV-B).

Per upload of vehicle ``n`` (every ``fusion.period`` steps from ``fusion.start[n]``) and per map
type: the BS map components inside the vehicle's accumulated FOV (its positions since its last
upload, radius :meth:`~mmslam.slam.specs.landmarks.LandmarkSpec.fov_radius`; only if the filter's
``p_D`` of the type, or with ``filter.pd_model = "beta"`` and ``pd_beta_downlink = "keep"`` the Gaussian's
own ``E[p_D]``, reaches ``fusion.gamma_detect``; with ``pd_beta_downlink = "prior"`` the type's prior mean,
the uploader's ``p_D`` of a landmark it does not hold) take part in the type's fusion operator
(AA fusion, eq. 8; VS: ego averaging, eq. 11, and VS fusion, eqs. 16-20, when the variant asks);
then the type's reduction. Between uploads, variants with ``predict_at_bs`` predict the maps of
types that have a BS predictor (VS, eq. 15, no birth). The downlink to vehicle ``n`` is the fused maps less the
first-detection landmarks that another car bore and that are not yet confirmed (:mod:`.confirmation`; the BS map
keeps them).
"""
from __future__ import annotations

import numpy as np

from mmslam.scenes.scenario import Scenario

from ..core.gm import GM, empty
from ..fusion.operators import ego_gaussian  # noqa: F401  (public here too)
from ..specs.landmarks import FusionInput, LandmarkSpec, landmark_types, vs_extent  # noqa: F401  (vs_extent: public here)
from ..specs.variants import VariantSpec, get_variant
from .confirmation import Confirmation, Unconfirmed


def filter_detect_probs(scn: Scenario) -> dict[int, float]:
    """Type code -> the filter's detection probability inside the FOV (``filter.p_detect_<type>``)."""
    return {s.code: s.p_detect(scn) for s in landmark_types()}


class FusionCenter:
    """The BS's fused maps (type code -> GM, batch ``()``) for one variant."""

    def __init__(self, scn: Scenario, variant: str | VariantSpec) -> None:
        self.scn = scn
        self.variant = get_variant(variant)
        self.specs: dict[int, LandmarkSpec] = {t.code: t for t in self.variant.types()}
        self.types = tuple(self.specs)
        # each type's fusion operator, chosen once by the variant (e.g. the proposed VS fusion)
        self.operators = {t: s.fusion_operator(self.variant) for t, s in self.specs.items()}
        self.maps: dict[int, GM] = {t: empty((), 0, s.state_dim) for t, s in self.specs.items()}
        self.confirmation = Confirmation(self.types)
        """the first-detection landmarks held back from the cars that did not bear them (:mod:`.confirmation`)"""

    def predict(self) -> None:
        """Variants with ``predict_at_bs``: predict every fused map whose type has a BS predictor (VS)."""
        if not self.variant.predict_at_bs:
            return
        for t, spec in self.specs.items():
            if spec.predict_at_bs is not None and self.maps[t].capacity:
                self.maps[t] = spec.predict_at_bs(self.maps[t], self.scn)

    def fuse(self, avg_maps: dict[int, GM], fov_positions: np.ndarray, ego_mean: np.ndarray,
             ego_cov: np.ndarray, vehicle: int | None = None,
             unconfirmed: Unconfirmed | None = None) -> dict[int, GM]:
        """Fuse one vehicle's upload into the BS maps; returns the maps to downlink to it: the fused maps less the
        first-detection landmarks another car bore that are not yet confirmed (:mod:`.confirmation`).

        Args:
            avg_maps: type code -> the vehicle's averaged map (batch ``()``).
            fov_positions: ``(n, 3)`` the vehicle's estimated positions since its last upload
                (accumulated FOV: radius ``fov_range`` for range-gated types, infinite otherwise).
            ego_mean, ego_cov: the vehicle's state posterior mean ``(7,)`` and covariance ``(7, 7)``.
            vehicle: the vehicle's index: its ego Gaussian's label in the VS map
                (:func:`mmslam.slam.core.gm.ego_label`, with ``fusion.average_by_label``); None: no label.
            unconfirmed: the vehicle's first-detection landmarks not yet detected at a second step
                (:attr:`LocalFilter.unconfirmed`); None: none.
        """
        from ..phd.detection import expected_pd
        from ..fusion.operators import in_accumulated_fov

        gamma = self.scn.fusion.gamma_detect
        ctx = FusionInput(self.scn, self.variant, ego_mean, ego_cov, vehicle)
        for t, spec in self.specs.items():
            bs_map = self.maps[t]
            ue = avg_maps.get(t, empty((), 0, spec.state_dim))
            # accumulated FOV (paper's footnote): where p_D reached gamma_D since the last upload
            inside = in_accumulated_fov(bs_map.m[..., 0:3], fov_positions, spec.fov_radius(self.scn.sensor))
            if bs_map.pd_beta is not None and self.scn.filter.pd_beta_downlink == "keep":
                # each Gaussian's own E[p_D] = s / (s + t), the history the vehicles share (pd_model beta)
                inside &= expected_pd(np.ones(bs_map.w.shape), bs_map.pd_beta) >= gamma
            else:
                # the uploading vehicle's p_D of a landmark it does not hold: the type's (with a Beta learnt
                # per vehicle, pd_beta_downlink = prior, its birth prior's mean; docs/city-slam.md)
                inside &= spec.p_detect(self.scn) >= gamma
            if unconfirmed is not None and vehicle is not None:
                self.confirmation.upload(t, vehicle, unconfirmed.labels.get(t, set()))
            fused, pairs = self.operators[t](bs_map, ue, inside, ctx)
            self.confirmation.fuse_pairs(t, fused, pairs)
            self.maps[t] = spec.reduce_fused(fused, pairs, self.scn, spec)
            self.confirmation.reduced(t, fused, self.maps[t], spec.merge_gate(self.scn))
        if vehicle is None:
            return dict(self.maps)
        return {t: self.confirmation.for_vehicle(t, g, vehicle) for t, g in self.maps.items()}
