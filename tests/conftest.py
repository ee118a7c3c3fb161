"""Shared pytest configuration: the hypothesis profile of the property tests.

``mmslam-ci`` (the default) is deterministic (``derandomize=True``: the same examples on every
run, so CI cannot flake on a new random draw), has no per-example deadline (shared CI cores make
timings meaningless) and a moderate example count that keeps ``tests/test_kernels_reference.py``
well under a minute on two shared cores. ``HYPOTHESIS_PROFILE=mmslam-deep`` runs a longer,
randomised search locally (e.g. after changing a kernel).
"""
from __future__ import annotations

import os

from hypothesis import HealthCheck, settings

settings.register_profile("mmslam-ci", max_examples=60, deadline=None, derandomize=True,
                          print_blob=True, suppress_health_check=[HealthCheck.too_slow])
settings.register_profile("mmslam-deep", max_examples=500, deadline=None, derandomize=False,
                          print_blob=True, suppress_health_check=[HealthCheck.too_slow])
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "mmslam-ci"))
