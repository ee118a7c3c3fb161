"""Padded Gaussian-mixture arrays: the one representation every filter stage shares.

A batch of mixtures (e.g. one per particle) is held as arrays with a leading batch shape ``B``
(``()`` for a single mixture, ``(P,)`` for one per particle):

- ``w``    ``(*B, Q)``        weights (PHD intensities, not normalised); 0 where masked out
- ``m``    ``(*B, Q, d)``     means (global frame, m; VS: ``[x, y, z, vx, vy, vz, xi]``)
- ``P``    ``(*B, Q, d, d)``  covariances, symmetric positive definite where ``mask``
- ``mask`` ``(*B, Q)``        True where the slot holds a component

Masked-out slots keep ``w = 0``, ``m = 0`` and ``P = I`` so any batched linear algebra on them
stays finite. Functions return new arrays (no in-place mutation of inputs).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class GM:
    """A batch of padded Gaussian mixtures (see module docstring for shapes)."""

    w: np.ndarray
    m: np.ndarray
    P: np.ndarray
    mask: np.ndarray

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
        return GM(self.w.copy(), self.m.copy(), self.P.copy(), self.mask.copy())

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


def empty(batch: tuple[int, ...], capacity: int, dim: int) -> GM:
    """An all-masked mixture batch."""
    w = np.zeros(batch + (capacity,))
    m = np.zeros(batch + (capacity, dim))
    P = np.broadcast_to(np.eye(dim), batch + (capacity, dim, dim)).copy()
    return GM(w, m, P, np.zeros(batch + (capacity,), bool))


def concat(a: GM, b: GM) -> GM:
    """Concatenate the component axis of two batches with the same batch shape and dim."""
    return GM(np.concatenate([a.w, b.w], -1), np.concatenate([a.m, b.m], -2),
              np.concatenate([a.P, b.P], -3), np.concatenate([a.mask, b.mask], -1))


def compact(g: GM, capacity: int | None = None) -> GM:
    """Move live components to the front (by descending weight) and trim to ``capacity`` slots.

    ``capacity`` defaults to the largest live count in the batch. Components beyond the
    capacity (the lowest weights) are dropped. Ties keep their slot order (stable sort). If the
    slots are already in that order (e.g. the output of a previous ``compact``), the result
    holds views of the input's leading slots instead of gathered copies.
    """
    key = np.where(g.mask, -g.w, np.inf)
    cap = int(g.count().max(initial=0)) if capacity is None else capacity
    cap = max(cap, 0)
    q = g.capacity
    if cap <= q and (q < 2 or bool((key[..., 1:] >= key[..., :-1]).all())):
        # identity permutation (a stable sort of non-decreasing keys): trim only
        mask = g.mask[..., :cap]
        return GM(np.where(mask, g.w[..., :cap], 0.0), g.m[..., :cap, :], g.P[..., :cap, :, :], mask)
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
    if k < cap:  # pad when capacity exceeds current slots
        pad = empty(B, cap - k, g.dim)
        return concat(GM(w, m, P, mask), pad)
    w = np.where(mask, w, 0.0)
    return GM(w, m, P, mask)


def symmetrize(P: np.ndarray) -> np.ndarray:
    """``(P + P^T) / 2`` over the last two axes."""
    return 0.5 * (P + np.swapaxes(P, -1, -2))


def select(g: GM, idx) -> GM:
    """Index the batch axes (e.g. ``select(g, p)`` for particle ``p``)."""
    return GM(g.w[idx], g.m[idx], g.P[idx], g.mask[idx])
