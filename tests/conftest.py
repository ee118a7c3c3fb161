"""Shared pytest configuration: the hypothesis profile of the property tests, and Ctrl-C for child processes.

``mmslam-ci`` (the default) is deterministic (``derandomize=True``: the same examples on every
run, so CI cannot flake on a new random draw), has no per-example deadline (shared CI cores make
timings meaningless) and a moderate example count that keeps ``tests/test_kernels_reference.py``
well under a minute on two shared cores. ``HYPOTHESIS_PROFILE=mmslam-deep`` runs a longer,
randomised search locally (e.g. after changing a kernel).

A suite started in the background of a non-interactive shell (``make test &``, ``nohup``) inherits
SIGINT *ignored*, and so would every ``mmslam`` process the tests start (an ignored disposition
survives ``exec``; Python then installs no Ctrl-C handler, rightly: the user asked for it to be
ignored). The fault tests send SIGINT to such processes and expect the ``interrupted:`` line: so
the suite restores Python's default handler for itself, which its children then start with.
"""
from __future__ import annotations

import os
import signal

from hypothesis import HealthCheck, settings

settings.register_profile("mmslam-ci", max_examples=60, deadline=None, derandomize=True,
                          print_blob=True, suppress_health_check=[HealthCheck.too_slow])
settings.register_profile("mmslam-deep", max_examples=500, deadline=None, derandomize=False,
                          print_blob=True, suppress_health_check=[HealthCheck.too_slow])
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "mmslam-ci"))

if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)
