"""Layer 2 of :mod:`mmslam.slam`, the GM-PHD building blocks of one map: the cubature Kalman update
(:mod:`.ckf`; its follow offset, :mod:`.follow`), the PHD correction and prediction (:mod:`.gmphd`, :mod:`.terms`:
eqs. 4-6, 10; its mass invariant, :mod:`.invariant`),
births from inverted measurements (:mod:`.birth`), mixture reduction and the averaged map
(:mod:`.reduction`, :mod:`.merging`: eq. 7) and the Beta detection model (:mod:`.detection`). They are
handed geometries, dimensions and type names by the caller; imports only ``core`` and ``models``.
"""
