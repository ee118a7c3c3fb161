"""The PHD-mass invariant of a correction (:func:`check_phd_mass`), checked by
:func:`mmslam.slam.phd.gmphd.correct` after every type's correction: per particle, the corrected mass is at most the
predicted mass plus the number of measurements."""
from __future__ import annotations

import numpy as np

from ..core.gm import GM
from .terms import _mass_bound_holds

PHD_MASS_RTOL = 1e-9
"""Relative float tolerance of :func:`check_phd_mass` (the bound is exact in real arithmetic)."""


def check_phd_mass(predicted: GM, corrected: GM, n_meas: int, name: str, step: int,
                   masses: tuple[np.ndarray, np.ndarray] | None = None) -> None:
    """Invariant of the PHD correction: per particle, corrected mass <= predicted mass + ``J``.

    The corrected intensity is ``(1 - p_D) D(x) + sum_j p_D g_j(x) D(x) / psi(z_j)`` and every
    ``psi(z_j)`` contains the clutter, the BS and all landmark terms of ``z_j``, so each
    measurement adds at most 1 to the mass: ``sum_q w_q^+ <= sum_q w_q + J`` (pruning only
    lowers the left side). A kernel that corrupts the log-weights breaks it at once (the
    ``_logsumexp_slots`` bug gave weights of ~1/clutter intensity). Cost: two sums over
    ``(P, Q)``, or none when the correction's kernels computed them (``masses``).

    Args:
        predicted: the map of one type before the correction, batch ``(P,)``.
        corrected: the same map after :func:`corrected_gm`, batch ``(P,)``.
        n_meas: the number of measurements ``J`` of the correction.
        name: the map's landmark type name (for the message); step: the time step ``k``.
        masses: ``(predicted, corrected)`` masses ``(P,)`` per particle (``sum w`` over the live
            slots) if already known (:attr:`TypeCorrection.pred_mass`, :func:`_corrected_components`);
            None: summed here from the maps.

    Raises:
        FloatingPointError: naming the type, step, particle and both masses, if the bound is
            exceeded beyond a relative ``PHD_MASS_RTOL`` (or a mass is NaN).
    """
    if masses is None:
        pred = np.where(predicted.mask, predicted.w, 0.0).sum(axis=-1)
        corr = np.where(corrected.mask, corrected.w, 0.0).sum(axis=-1)
    else:
        pred, corr = (np.asarray(a, float) for a in masses)
        if not pred.shape == corr.shape == predicted.w.shape[:-1]:  # the kernel reads corr[p] unchecked
            raise ValueError(f"check_phd_mass: masses of shapes {pred.shape}, {corr.shape}; expected the maps' "
                             f"batch shape {predicted.w.shape[:-1]} for both")
        if _mass_bound_holds(pred.reshape(-1), corr.reshape(-1), float(n_meas), PHD_MASS_RTOL):  # one compiled pass
            return
    bound = pred + n_meas
    bad = ~(corr <= bound * (1.0 + PHD_MASS_RTOL))  # NaN fails too
    if bad.any():
        p = int(np.argmax(np.where(bad, np.nan_to_num(corr - bound, nan=np.inf), -np.inf)))
        raise FloatingPointError(
            f"PHD mass invariant violated in the {name} correction at step {step}, particle {p}: "
            f"corrected mass {corr[p]:.6g} > predicted mass {pred[p]:.6g} + {n_meas} measurements "
            f"({int(bad.sum())} of {bad.size} particles); a correction kernel corrupted the weights")
