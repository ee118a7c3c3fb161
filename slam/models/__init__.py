"""Layer 1 of :mod:`mmslam.slam`, the paper's models of one point: the vehicle and VS motion models
(:mod:`.dynamics`, :mod:`.vs`: eqs. 1-2, 9, 15), the measurement function of a path geometry
(:mod:`.measurement`: eq. 3) and the simulated sensor (:mod:`.sensor`: detection, noise, clutter).
Functions take a path geometry (:class:`mmslam.model.Bounce`), dimensions and per-type data as
arguments, never a landmark type to look up; imports only :mod:`mmslam.slam.core` below it.
"""
