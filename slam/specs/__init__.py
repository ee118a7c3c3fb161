"""Layer 3 of :mod:`mmslam.slam`, the specs: one small registry of landmark types
(:mod:`.landmarks`: name, code, geometry, dimension, FOV gate, per-type parameters, and the
prediction / birth / fusion / reduction functions built from ``phd`` and ``fusion``) and one of
variants (:mod:`.variants`: which maps, which fusion operators). A new type or variant is one module
that registers a spec (docs/extending.md); nothing below this layer looks a type up here.
"""
