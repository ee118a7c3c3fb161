"""Layer 2 of :mod:`mmslam.slam`, plain textbook reference implementations of the compiled kernels
(one Gaussian, one measurement at a time, NumPy / SciPy only): the measurement function, the
cubature Kalman update, the GM-PHD correction and the greedy mixture reduction. Never used by the
filter; the tests (``tests/test_kernels_reference.py``) check the fast kernels against them and
docs/equations.md names both for every equation. Imports only ``core`` and ``models``.
"""
