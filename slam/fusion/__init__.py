"""Layer 2 of :mod:`mmslam.slam`, the map-fusion operators at the BS (:mod:`.operators`): AA fusion
with MSM matching (eq. 8), the ego Gaussian and ego-VS averaging (eq. 11), VS prediction at the BS
(eq. 15), the VS fusion of eqs. 16-20, ego removal on the downlink and the accumulated FOV. Pure
functions of Gaussian mixtures and parameters; imports only ``core`` and ``models``.
"""
