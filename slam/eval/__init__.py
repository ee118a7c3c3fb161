"""Layer 4 of :mod:`mmslam.slam`, evaluation: the truth visible to each map, estimate extraction,
cardinality and GOSPA rows per step, map and type (:mod:`.evaluation`) and the GOSPA metric itself
(:mod:`.gospa`), and the step viewer of one run (:mod:`.viewer`: per-step frames of vehicles, a
map's estimates vs truth and the traced paths, as self-contained HTML or an animation). Reads the
type specs; imports nothing of the run loop.
"""
