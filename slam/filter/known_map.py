"""A known landmark map handed to the filter: localisation with a given map, the upper bound of what a map helps.

SLAM estimates the map and localises on it at once. How much the map of one type (the VAs of a street, say)
can help the vehicles localise at best is measured by giving each vehicle, before every correction, the
true landmarks of that type it has a path to at that step (:class:`KnownMap`), optionally with a fixed
position error per landmark: a map as good as the truth, or as good as a mapping error of ``error_std``
metres. The filter keeps everything else (its own maps of the other types, births, fusion); the known
type's map is overwritten at every step, so its births and fused copies play no part.

This is an oracle for experiments (``benchmarks/city_va.py --known-va``), not a mode of the SLAM filter:
it reads the true landmark positions from the path table.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mmslam.errors import MmslamError

from ..core.gm import GM, NO_LABEL


KNOWN_MIN_STD = 0.05
"""Position std (m) the filter is given for an exact known map (``error_std = 0``): a covariance of 0 would
make the CKF's cubature points collapse, and 5 cm is below the TOA noise (0.1 m) of every preset."""


@dataclass(frozen=True)
class KnownMap:
    """The landmarks of one type each vehicle is given at each step.

    Attributes:
        type_code: the landmark type (``paths.type`` code) whose map is replaced.
        step, vehicle: ``(N,)`` int, the step and receiving vehicle of each row.
        position: ``(N, 3)`` landmark position (m, world frame), the truth plus its landmark's error.
        std: position std (m) of every known landmark, the covariance ``std^2 I`` the filter is given.
        p_detect: detection probability the filter uses for a known landmark (its Beta mean, count 20).
    """

    type_code: int
    step: np.ndarray
    vehicle: np.ndarray
    position: np.ndarray
    std: float
    p_detect: float

    def at(self, step: int, vehicle: int) -> np.ndarray:
        """``(Q, 3)`` the known landmarks of ``vehicle`` at ``step`` (each once)."""
        sel = (self.step == step) & (self.vehicle == vehicle)
        return np.unique(self.position[sel], axis=0)

    def mixture(self, step: int, vehicle: int, particles: int, with_pd_beta: bool, with_label: bool) -> GM:
        """The known map of ``vehicle`` at ``step`` as every particle's GM: batch ``(particles,)``, ``Q`` slots,
        weight 1, mean the known position, covariance ``std^2 I``; Beta ``(20 p, 20 (1 - p))`` of mean
        ``p_detect`` (if ``with_pd_beta``); labels (if ``with_label``) NO_LABEL: a known landmark is no
        vehicle's birth."""
        pts = self.at(step, vehicle)
        P, Q = int(particles), len(pts)
        pd_beta = np.broadcast_to([20.0 * self.p_detect, 20.0 * (1.0 - self.p_detect)], (P, Q, 2)).copy() \
            if with_pd_beta else None
        label = np.full((P, Q), NO_LABEL, np.int64) if with_label else None
        return GM(np.ones((P, Q)), np.broadcast_to(pts, (P, Q, 3)).copy(),
                  np.broadcast_to(np.eye(3) * self.std ** 2, (P, Q, 3, 3)).copy(), np.ones((P, Q), bool),
                  pd_beta, label)


def known_map(paths: dict[str, np.ndarray], type_code: int, error_std: float, p_detect: float,
              rng: np.random.Generator) -> KnownMap:
    """The known map of one type from a path table: every ``(step, rx)`` row of that type is a landmark the
    vehicle ``rx`` is given at that step.

    Args:
        paths: ``paths`` table columns (``step``, ``rx``, ``type``, ``landmark_id``, ``lm_x/y/z``).
        type_code: the landmark type (e.g. ``VA_SPEC.code``).
        error_std: std (m) of a fixed position error per landmark (``landmark_id``), drawn once from ``rng``
            (isotropic, 3-D): the mapping error of the map; 0 gives the truth. The filter is given the
            covariance ``max(error_std, KNOWN_MIN_STD)^2 I``, the error's own (an honest map).
        p_detect: detection probability of a known landmark (:attr:`KnownMap.p_detect`), in (0, 1).
        rng: draws the landmarks' errors (in sorted ``landmark_id`` order).

    Raises:
        MmslamError: ``error_std < 0`` or ``p_detect`` outside (0, 1).
    """
    if not error_std >= 0.0:
        raise MmslamError(f"known map error_std={error_std}: expected a std >= 0 (m)")
    if not 0.0 < p_detect < 1.0:
        raise MmslamError(f"known map p_detect={p_detect}: expected a probability in (0, 1)")
    sel = np.asarray(paths["type"]) == type_code
    pos = np.stack([np.asarray(paths[c], float)[sel] for c in ("lm_x", "lm_y", "lm_z")], axis=-1)
    ids = np.asarray(paths["landmark_id"]).astype(str)[sel]
    names, inverse = np.unique(ids, return_inverse=True)
    err = rng.standard_normal((len(names), 3)) * error_std if error_std > 0 else np.zeros((len(names), 3))
    return KnownMap(int(type_code), np.asarray(paths["step"])[sel].astype(int), np.asarray(paths["rx"])[sel].astype(int),
                    pos + err[inverse.reshape(-1)], max(float(error_std), KNOWN_MIN_STD), float(p_detect))
