"""Cooperative MM-PHD-SLAM (public names; the implementation is split by role).

- :mod:`mmslam.slam.specs.landmarks`: one spec per landmark type (VA, SP, VS, ...); :mod:`mmslam.slam.specs.variants`:
  one spec per variant (``odometry``, ``baseline``, ``cm1``, ``proposed``);
- :mod:`mmslam.slam.filter.local_filter`: the per-vehicle RBPF (:class:`LocalFilter`, :class:`StepEstimate`);
- :mod:`mmslam.slam.filter.fusion_center`: the BS (:class:`FusionCenter`, :func:`ego_gaussian`);
- :mod:`mmslam.slam.eval.evaluation`: truth, estimates, GOSPA rows;
- :mod:`mmslam.slam.filter.run`: the run loop (:class:`CooperativeRun`, :func:`run_filter`, :func:`run_slam`).
"""
from __future__ import annotations

from ..eval.evaluation import (EXTRACTIONS, VA_KEY_RESOLUTION, cardinality, estimates_of, first_seen,  # noqa: F401
                         truth_keys, visible_counts)
from .fusion_center import FusionCenter, ego_gaussian, filter_detect_probs, vs_extent  # noqa: F401
from .local_filter import LocalFilter, StepEstimate  # noqa: F401
from .run import CooperativeRun, run_filter, run_slam, schedule  # noqa: F401
from ..specs.variants import REFERENCES, VARIANTS, VariantSpec, get_variant  # noqa: F401

__all__ = ["EXTRACTIONS", "VA_KEY_RESOLUTION", "cardinality", "estimates_of", "first_seen", "truth_keys",
           "visible_counts", "FusionCenter", "ego_gaussian", "filter_detect_probs", "vs_extent", "LocalFilter",
           "StepEstimate", "CooperativeRun", "run_filter", "run_slam", "schedule", "REFERENCES", "VARIANTS",
           "VariantSpec", "get_variant"]
