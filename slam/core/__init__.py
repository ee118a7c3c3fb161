"""Layer 0 of :mod:`mmslam.slam`, the compiled plumbing: numba kernel options (:mod:`.jit`), small
batched linear algebra (:mod:`.linalg`: Cholesky, triangular solves, SPD inverses), fast scalar
trigonometry (:mod:`.trig`), the padded Gaussian-mixture arrays every filter stage shares
(:mod:`.gm`) and the allocator setting of long runs (:mod:`.memory`). Knows nothing of landmarks,
types or the paper's models; imports nothing else from ``slam/`` (docs/architecture.md).
"""
