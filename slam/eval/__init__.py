"""Layer 4 of :mod:`mmslam.slam`, evaluation: the truth visible to each map, estimate extraction,
cardinality and GOSPA rows per step, map and type (:mod:`.evaluation`) and the GOSPA metric itself
(:mod:`.gospa`). Reads the type specs; imports nothing of the run loop.
"""
