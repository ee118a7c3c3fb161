"""Layer 4 of :mod:`mmslam.slam`, the simulated sensor (:mod:`.sensor`): the measurement sets a
vehicle receives from a path cache (detection inside the FOV, noise, clutter, the power-aware link
budget) and the FOV detection probability the filter and the evaluation share. It applies the
registered landmark types' FOV rules, so it sits above ``specs``.
"""
