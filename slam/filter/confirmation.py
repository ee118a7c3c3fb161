"""First-detection landmarks reach the other cars only once confirmed (``filter.types.<T>.birth_existence``).

A birth that is a new landmark by its own measurement (:mod:`~mmslam.slam.phd.first_detection`) is mapped from its
first detection, at the position one car's particles put it. The car that saw it uses it at once (its own SLAM); the
fused map at the BS holds it too (the map a user reads). Another car gets it through the downlink only once it is
confirmed, that is detected at a second step:

- by the car that bore it: the Beta detection count of its averaged copy (``GM.pd_beta``, ``filter.pd_model =
  "beta"``) rose by at least a half above the type's prior ``s0`` (:func:`detected_since_birth`). A detection adds 1
  to ``s`` of the detection term; the averaged copy pools it with the missed term by weight, so one clean detection
  adds ``w_d / (w_d + w_m)``: about 0.53 for a landmark of weight 0.9 under the Bernoulli missed rule at ``p_D`` 0.1
  (missed weight 0.89). A detection that another explanation shares (clutter, another landmark) may add less, and
  then waits for the next;
- or by another car (or by the same car under another label): at the BS the fusion matched it with a landmark of
  another label (:meth:`Confirmation.fuse_pairs`), or the fused map's reduction merged one into it
  (:meth:`Confirmation.reduced`).

Book-keeping by label (``fusion.average_by_label``; a birth's label is the same in every particle and names the car
that bore it, ``label >> LABEL_BITS``); without labels or without a Beta detection model nothing is withheld.
Sets of labels per type code: the car's :class:`Unconfirmed` and the BS's :class:`Confirmation`.
"""
from __future__ import annotations

import numpy as np

from ..core.gm import LABEL_BITS, GM


def fresh_labels(born: GM, birth_weight: float) -> np.ndarray:
    """Labels ``(n,)`` of the birth slots that are new landmarks: weighted above ``birth_weight`` (``filter.birth_weight``)
    in some particle. A birth weighs ``birth_weight`` times ``c / psi <= 1`` unless it is new (``birth_existence``
    times the same), so this is exactly the slots born new in a particle whose ``c / psi`` exceeds
    ``birth_weight / birth_existence``. ``born``: batch ``(P,)``, labelled."""
    if born.label is None or not born.capacity:
        return np.zeros(0, np.int64)
    new = (born.mask & (born.w > birth_weight)).any(axis=0)
    return np.unique(born.label[..., new][born.mask[..., new]])


def detected_since_birth(avg: GM, prior_s: float) -> np.ndarray:
    """Labels of the averaged map's components (batch ``()``) detected at a step after their birth: Beta ``s`` at least
    ``prior_s + 0.5`` (``prior_s``: the type's prior ``s0``, :func:`~mmslam.slam.phd.detection.prior_beta`)."""
    if avg.label is None or avg.pd_beta is None or not avg.capacity:
        return np.zeros(0, np.int64)
    return avg.label[avg.mask & (avg.pd_beta[..., 0] >= prior_s + 0.5)]


def owner(labels: np.ndarray) -> np.ndarray:
    """The vehicle index that bore each label (``label >> LABEL_BITS``)."""
    return np.asarray(labels, np.int64) >> LABEL_BITS


class Unconfirmed:
    """One car's first-detection landmarks not yet detected at a second step: type code -> set of labels."""

    def __init__(self, types: tuple[int, ...]) -> None:
        self.labels: dict[int, set[int]] = {t: set() for t in types}

    def born(self, t: int, labels: np.ndarray) -> None:
        """Record the labels of type ``t``'s births that are new landmarks (:func:`fresh_labels`)."""
        self.labels[t].update(int(x) for x in labels)

    def detected(self, t: int, labels: np.ndarray) -> None:
        """Drop the labels of type ``t`` detected since their birth (:func:`detected_since_birth`)."""
        if self.labels[t]:
            self.labels[t].difference_update(int(x) for x in labels)


class Confirmation:
    """The BS's view: per type code the labels withheld from the cars that did not bear them, and those confirmed."""

    def __init__(self, types: tuple[int, ...]) -> None:
        self.held: dict[int, set[int]] = {t: set() for t in types}
        self.confirmed: dict[int, set[int]] = {t: set() for t in types}

    def upload(self, t: int, vehicle: int, unconfirmed: set[int]) -> None:
        """Vehicle ``vehicle``'s upload of type ``t``: its own labels held are exactly those it still calls
        unconfirmed (less any the BS confirmed by a match)."""
        held = self.held[t]
        mine = {x for x in held if x >> LABEL_BITS == vehicle}
        held.difference_update(mine)
        held.update(unconfirmed - self.confirmed[t])

    def fuse_pairs(self, t: int, union: GM, pairs: np.ndarray | None) -> None:
        """The fusion's matched ``pairs (n, 2)`` (slots of ``union``, batch ``()``): a pair of two labels is one
        landmark seen twice, so both labels are confirmed."""
        if pairs is None or not len(pairs) or union.label is None or not self.held[t]:
            return
        a, b = union.label[pairs[:, 0]], union.label[pairs[:, 1]]
        two = (a != b) & (a >= 0) & (b >= 0)
        if two.any():
            both = {int(x) for x in np.concatenate([a[two], b[two]])}
            self.confirmed[t].update(both & self.held[t])
            self.held[t].difference_update(both)

    def reduced(self, t: int, union: GM, out: GM, gate: float) -> None:
        """After the fused map's reduction ``union -> out`` (batch ``()``, merge gate ``gate``, squared Mahalanobis in
        position): a held landmark of ``out`` whose gate holds a union component of another label (>= 0) took that
        landmark in (the merged Gaussian keeps the heavier member's label), so it is confirmed: otherwise a landmark
        already shared would vanish from the other cars' downlinks inside a held one."""
        held = self.held[t]
        if not held or union.label is None or out.label is None or not out.capacity or not union.capacity:
            return
        mine = np.flatnonzero(out.mask & np.isin(out.label, np.fromiter(held, np.int64, len(held))))
        other = union.mask & (union.label >= 0)
        for i in mine:
            cand = other & (union.label != out.label[i])
            if not cand.any():
                continue
            d = union.m[cand][:, 0:3] - out.m[i, 0:3]
            q = np.einsum("ni,ij,nj->n", d, np.linalg.inv(out.P[i, 0:3, 0:3]), d)
            if (q <= gate).any():
                lab = int(out.label[i])
                held.discard(lab)
                self.confirmed[t].add(lab)

    def for_vehicle(self, t: int, g: GM, vehicle: int) -> GM:
        """The fused map ``g`` (batch ``()``) without the held landmarks another car bore: the downlink to ``vehicle``."""
        held = self.held[t]
        if not held or g.label is None or not g.capacity:
            return g
        lab = g.label
        drop = g.mask & np.isin(lab, np.fromiter(held, np.int64, len(held))) & (owner(lab) != vehicle)
        return g if not drop.any() else g.take(np.flatnonzero(~drop))
