"""Padded Gaussian-mixture arrays: the one representation every filter stage shares.

A batch of mixtures (e.g. one per particle) is held as arrays with a leading batch shape ``B``
(``()`` for a single mixture, ``(P,)`` for one per particle):

- ``w``    ``(*B, Q)``        weights (PHD intensities, not normalised); 0 where masked out
- ``m``    ``(*B, Q, d)``     means (global frame, m; VS: ``[x, y, z, vx, vy, vz, xi]``)
- ``P``    ``(*B, Q, d, d)``  covariances, symmetric positive definite where ``mask``
- ``mask`` ``(*B, Q)``        True where the slot holds a component
- ``pd_beta`` ``(*B, Q, 2)`` optional: the Beta(s, t) parameters of each component's own detection
  probability (``filter.pd_model = "beta"``, :mod:`mmslam.slam.phd.detection`); None for a fixed ``p_D``.
  Masked slots hold (1, 1). Every operation here carries it with its component.
- ``label`` ``(*B, Q)`` optional int64: an identity per component (``fusion.average_by_label``): a birth
  gets one label in every particle, a corrected component its predicted slot's, a merged one its
  cluster leader's (the largest weight), so the particles' copies of one landmark share a label
  (:func:`mmslam.slam.phd.reduction.average_map` pools them). None when not tracked; masked slots hold
  -1 (:data:`NO_LABEL`, no identity: never pooled). Every operation here carries it like ``pd_beta``.

Masked-out slots keep ``w = 0``, ``m = 0`` and ``P = I`` so any batched linear algebra on them
stays finite. Functions return new arrays (no in-place mutation of inputs).
"""
from __future__ import annotations

from dataclasses import dataclass

import numba as nb
import numpy as np


@dataclass
class GM:
    """A batch of padded Gaussian mixtures (see module docstring for shapes)."""

    w: np.ndarray
    m: np.ndarray
    P: np.ndarray
    mask: np.ndarray
    pd_beta: np.ndarray | None = None
    label: np.ndarray | None = None

    @property
    def dim(self) -> int:
        return self.m.shape[-1]

    @property
    def capacity(self) -> int:
        return self.w.shape[-1]

    @property
    def batch_shape(self) -> tuple[int, ...]:
        return self.w.shape[:-1]

    def count(self) -> np.ndarray:
        """Number of live components per mixture, shape ``B``."""
        return self.mask.sum(axis=-1)

    def copy(self) -> "GM":
        return GM(self.w.copy(), self.m.copy(), self.P.copy(), self.mask.copy(),
                  None if self.pd_beta is None else self.pd_beta.copy(),
                  None if self.label is None else self.label.copy())

    def take(self, idx) -> "GM":
        """``GM(w[idx], m[idx], P[idx], mask[idx], pd_beta[idx], label[idx])``: the same index on every array."""
        return GM(self.w[idx], self.m[idx], self.P[idx], self.mask[idx],
                  None if self.pd_beta is None else self.pd_beta[idx],
                  None if self.label is None else self.label[idx])

    def check(self, where: str = "") -> None:
        """Raise FloatingPointError if a live component has a NaN/inf weight, mean or covariance."""
        if np.isfinite(self.w).all() and np.isfinite(self.m).all() and np.isfinite(self.P).all():
            return  # fast path: everything (live or not) finite
        live = self.mask
        bad = ~np.isfinite(self.w) & live
        bad |= ~np.isfinite(self.m).all(-1) & live
        bad |= ~np.isfinite(self.P).all((-1, -2)) & live
        if bad.any():
            raise FloatingPointError(f"non-finite Gaussian component {where}".strip())


NO_LABEL = -1
"""The ``label`` of a masked slot and of a component without identity."""

LABEL_BITS = 40
"""Vehicle ``n``'s labels are ``n << LABEL_BITS`` ... ``(n + 1) << LABEL_BITS`` - 1: its births from the
first (:class:`~mmslam.slam.filter.local_filter.LocalFilter`), its own Gaussian in the VS maps the last
(:func:`ego_label`)."""


def ego_label(vehicle: int) -> int:
    """The label of vehicle ``vehicle``'s own Gaussian in the VS maps (``F'_AA``, eq. (11)): the last of
    its label range, which its births (from ``vehicle << LABEL_BITS`` on) do not reach. The same in
    every upload: after a downlink another vehicle's particles hold copies of it, pooled by label."""
    return ((int(vehicle) + 1) << LABEL_BITS) - 1


def is_ego_label(label: np.ndarray) -> np.ndarray:
    """Whether each label (any shape, int64) is some vehicle's :func:`ego_label`: the last of its range (its low
    :data:`LABEL_BITS` all set), which no birth takes; :data:`NO_LABEL` is not. In a VS map: a car's own estimate
    (another car's, downlinked). Returns a bool array of the labels' shape."""
    label = np.asarray(label, np.int64)
    low = (1 << LABEL_BITS) - 1
    return (label >= 0) & ((label & low) == low)


def empty(batch: tuple[int, ...], capacity: int, dim: int, with_pd_beta: bool = False,
          with_label: bool = False) -> GM:
    """An all-masked mixture batch (``with_pd_beta``: with a ``pd_beta`` array of (1, 1) slots;
    ``with_label``: with a ``label`` array of :data:`NO_LABEL`)."""
    w = np.zeros(batch + (capacity,))
    m = np.zeros(batch + (capacity, dim))
    P = np.broadcast_to(np.eye(dim), batch + (capacity, dim, dim)).copy()
    pd_beta = np.ones(batch + (capacity, 2)) if with_pd_beta else None
    label = np.full(batch + (capacity,), NO_LABEL, np.int64) if with_label else None
    return GM(w, m, P, np.zeros(batch + (capacity,), bool), pd_beta, label)


def _beta_or_fill(g: GM, other: GM) -> np.ndarray | None:
    """``g.pd_beta``, or (1, 1) slots when only ``other`` carries one and ``g`` has no slots.

    Raises ValueError if ``g`` has slots and no ``pd_beta`` while ``other`` has one (a component
    would lose its detection history)."""
    if g.pd_beta is not None or other.pd_beta is None:
        return g.pd_beta
    if g.capacity:
        raise ValueError("cannot join a mixture with Beta detection parameters and one without")
    return np.ones(g.batch_shape + (0, 2))


def concat_pd_beta(a: GM, b: GM) -> np.ndarray | None:
    """The ``pd_beta`` of :func:`concat` ``(a, b)``: both joined on the component axis, or None."""
    ba, bb = _beta_or_fill(a, b), _beta_or_fill(b, a)
    return None if ba is None else np.concatenate([ba, bb], -2)


def _label_or_fill(g: GM, other: GM) -> np.ndarray | None:
    """``g.label``, or an empty label array when only ``other`` carries one and ``g`` has no slots.

    Raises ValueError if ``g`` has slots and no ``label`` while ``other`` has one."""
    if g.label is not None or other.label is None:
        return g.label
    if g.capacity:
        raise ValueError("cannot join a mixture with component labels and one without")
    return np.full(g.batch_shape + (0,), NO_LABEL, np.int64)


def concat_label(a: GM, b: GM) -> np.ndarray | None:
    """The ``label`` of :func:`concat` ``(a, b)``: both joined on the component axis, or None."""
    la, lb = _label_or_fill(a, b), _label_or_fill(b, a)
    return None if la is None else np.concatenate([la, lb], -1)


def concat(a: GM, b: GM) -> GM:
    """Concatenate the component axis of two batches with the same batch shape and dim."""
    return GM(np.concatenate([a.w, b.w], -1), np.concatenate([a.m, b.m], -2),
              np.concatenate([a.P, b.P], -3), np.concatenate([a.mask, b.mask], -1), concat_pd_beta(a, b),
              concat_label(a, b))


def with_labels(g: GM, first: int) -> tuple[GM, int]:
    """``g`` with the labels ``first, first + 1, ...`` of its slots, the same in every mixture of the
    batch (slot ``q`` of every particle's births is one landmark hypothesis); masked slots
    :data:`NO_LABEL`. Returns the labelled mixture and the next free label."""
    lab = np.broadcast_to(np.arange(first, first + g.capacity, dtype=np.int64), g.w.shape)
    return (GM(g.w, g.m, g.P, g.mask, g.pd_beta, np.where(g.mask, lab, NO_LABEL)), first + g.capacity)


def compact(g: GM, capacity: int | None = None) -> GM:
    """Move live components to the front (by descending weight) and trim to ``capacity`` slots.

    ``capacity`` defaults to the largest live count in the batch. Components beyond the
    capacity (the lowest weights) are dropped. Ties keep their slot order (stable sort). If the
    slots are already in that order (e.g. the output of a previous ``compact``), the result
    holds views of the input's leading slots instead of gathered copies.
    """
    if g.label is not None and np.shape(g.label) != g.w.shape:  # np.where would broadcast a (P, 1) label
        raise ValueError(f"GM.label has shape {np.shape(g.label)}; expected the weights' {g.w.shape}")
    key = np.where(g.mask, -g.w, np.inf)
    cap = int(g.count().max(initial=0)) if capacity is None else capacity
    cap = max(cap, 0)
    q = g.capacity
    if cap <= q and (q < 2 or bool((key[..., 1:] >= key[..., :-1]).all())):
        # identity permutation (a stable sort of non-decreasing keys): trim only
        mask = g.mask[..., :cap]
        return GM(np.where(mask, g.w[..., :cap], 0.0), g.m[..., :cap, :], g.P[..., :cap, :, :], mask,
                  None if g.pd_beta is None else g.pd_beta[..., :cap, :],
                  None if g.label is None else np.where(mask, g.label[..., :cap], NO_LABEL))
    order = np.argsort(key, axis=-1, kind="stable")[..., :cap]
    B = g.batch_shape
    n = int(np.prod(B, dtype=int))
    k = order.shape[-1]
    o = order.reshape(n, k)
    rows = np.arange(n)[:, None]
    w = g.w.reshape(n, q)[rows, o].reshape(B + (k,))
    mask = g.mask.reshape(n, q)[rows, o].reshape(B + (k,))
    m = g.m.reshape(n, q, g.dim)[rows, o].reshape(B + (k, g.dim))
    P = g.P.reshape(n, q, g.dim, g.dim)[rows, o].reshape(B + (k, g.dim, g.dim))
    pd_beta = None if g.pd_beta is None else g.pd_beta.reshape(n, q, 2)[rows, o].reshape(B + (k, 2))
    label = None if g.label is None else g.label.reshape(n, q)[rows, o].reshape(B + (k,))
    out = GM(np.where(mask, w, 0.0), m, P, mask, pd_beta, None if label is None else np.where(mask, label, NO_LABEL))
    if k < cap:  # pad when capacity exceeds current slots
        return concat(out, empty(B, cap - k, g.dim, g.pd_beta is not None, g.label is not None))
    return out


@nb.njit(cache=True)
def live_slots(mask: np.ndarray, idx: np.ndarray) -> int:
    """The slots ``q`` of ``mask (N, Q)`` live in some mixture, in order, written to ``idx[:count]``
    (``idx (Q,)`` int64); returns the count."""
    count = 0
    for q in range(mask.shape[1]):
        for n in range(mask.shape[0]):
            if mask[n, q]:
                idx[count] = q
                count += 1
                break
    return count


def drop_dead_slots(g: GM) -> GM:
    """``g`` without the slots that are masked in every mixture of the batch (the others keep their
    order); ``g`` itself if there are none."""
    q = g.capacity
    if np.shape(g.mask) != np.shape(g.w):
        raise ValueError(f"GM.mask has shape {np.shape(g.mask)}; expected the weights' {np.shape(g.w)}")
    if not q:
        return g
    idx = np.empty(q, np.int64)
    n_live = live_slots(g.mask.reshape(-1, q), idx)
    if n_live == q:
        return g
    idx = idx[:n_live]
    return GM(np.take(g.w, idx, -1), np.take(g.m, idx, -2), np.take(g.P, idx, -3), np.take(g.mask, idx, -1),
              None if g.pd_beta is None else np.take(g.pd_beta, idx, -2),
              None if g.label is None else np.take(g.label, idx, -1))


def symmetrize(P: np.ndarray) -> np.ndarray:
    """``(P + P^T) / 2`` over the last two axes."""
    return 0.5 * (P + np.swapaxes(P, -1, -2))


def random_walk(g: GM, var: float, dims: int = 3) -> GM:
    """The components of ``g`` after one step of a random walk of their first ``dims`` state entries (the position,
    m): ``P + var I`` on that block of every live component, ``var`` (m^2) the walk's variance over the step; weights,
    means, the rest of ``P``, ``pd_beta`` and labels as they are, masked slots untouched (``P = I``). New arrays."""
    P = g.P.copy()
    idx = np.arange(dims)
    P[..., idx, idx] += np.where(g.mask, float(var), 0.0)[..., None]
    return GM(g.w, g.m, P, g.mask, g.pd_beta, g.label)


def select(g: GM, idx) -> GM:
    """Index the batch axes (e.g. ``select(g, p)`` for particle ``p``)."""
    return g.take(idx)


@nb.njit(cache=True, error_model="numpy", inline="always")
def finite_gaussian(w: float, m: np.ndarray, P: np.ndarray) -> bool:
    """True if the weight ``w``, mean ``m (d,)`` and covariance ``P (d, d)`` are all finite."""
    ok = np.isfinite(w)
    for a in range(m.shape[0]):
        ok &= np.isfinite(m[a])
        for b in range(m.shape[0]):
            ok &= np.isfinite(P[a, b])
    return ok


@nb.njit(cache=True, error_model="numpy", inline="always")
def dead_gaussian(m: np.ndarray, P: np.ndarray) -> None:
    """A masked slot's ``m (d,) = 0`` and ``P (d, d) = I`` (the :mod:`mmslam.slam.core.gm` convention)."""
    for a in range(m.shape[0]):
        m[a] = 0.0
        for b in range(m.shape[0]):
            P[a, b] = 1.0 if a == b else 0.0
