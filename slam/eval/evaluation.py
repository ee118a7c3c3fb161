"""Evaluation of a cooperative run: ground truth per map, landmark estimates, GOSPA rows (docs/design.md section 5).

Truth of a map of type ``t`` at step ``k`` (:class:`MapScorer`):

- static types (VA, SP): every landmark the vehicle could have detected so far, i.e. present in
  its paths *and* inside its FOV at some step ``<= k`` (:func:`first_seen`); the fused map's truth
  is the union over vehicles; a vehicle's map after a downlink holds the fused map, so its truth also
  holds every landmark some vehicle could have detected by the step of its last downlink
  (:meth:`MapScorer.record_downlink`, :func:`truth_union`); a VA of order 2 (a double specular bounce,
  ``bounces = 2``, landmark the image of an image: docs/estimator.md) is a VA like one of order 1 (a fixed point
  the filter can map), keyed by its image position like every VA (:func:`truth_keys`), in the truth and the
  visible counts alike;
- moving types (VS): the other vehicles within the FOV radius of the vehicle at step ``k``;
  for the fused map, every vehicle.

Estimates (:func:`estimates_of`): the averaged map's components above the type's threshold
``filter.threshold_<type>`` (or ``filter.extraction = vo_ma``). Scores: GOSPA (p, c, alpha of
``[evaluation]``) on 3-D positions, plus the cardinality (sum of weights) and the number of
landmarks visible at ``k`` (:func:`visible_counts`).
"""
from __future__ import annotations

from typing import Any

import numpy as np

from mmslam.errors import MmslamError
from mmslam.model import Bounce

from ..core.gm import GM
from ..specs.landmarks import LandmarkSpec, mapped_types

EXTRACTIONS = ("threshold", "vo_ma")
VA_KEY_RESOLUTION = 1e-3
"""m: VAs whose image sources agree to this are one landmark (facades of several objects on one plane)."""
VA_RESOLUTION = 1.0
"""m, the default of ``evaluation.va_resolution``: image sources closer than this count as one VA (two
parallel facades less than 0.5 m apart; docs/city-slam.md)."""

Seen = dict[str, tuple[int, np.ndarray]]
"""landmark key -> (first step it could be detected, position ``(3,)`` m)."""


def estimates_of(g: GM, threshold: float, extraction: str = "threshold") -> tuple[np.ndarray, np.ndarray]:
    """Landmark estimates of one mixture: positions ``(n, 3)`` and the weight of the Gaussian behind each.

    ``threshold`` (TWC2020): one estimate per component with ``w > threshold``.
    ``vo_ma`` (Vo & Ma 2006, Table III): ``round(w)`` estimates at the mean of each component with
    ``w > 0.5``, so a Gaussian of weight ~2 (two merged targets) counts twice.
    """
    if extraction not in EXTRACTIONS:
        raise MmslamError(f"extraction={extraction!r}: expected one of {', '.join(EXTRACTIONS)}")
    if extraction == "threshold":
        sel = g.mask & (g.w > threshold)
        return g.m[sel][:, 0:3], g.w[sel]
    sel = np.nonzero(g.mask & (g.w > 0.5))[0]
    reps = np.maximum(np.rint(g.w[sel]).astype(int), 1)
    idx = np.repeat(sel, reps)
    return g.m[idx][:, 0:3], g.w[idx]


def cardinality(g: GM) -> float:
    """Expected number of landmarks of a map PHD: the sum of its weights."""
    return float(np.sum(np.where(g.mask, g.w, 0.0)))


def evaluated_types() -> tuple[LandmarkSpec, ...]:
    """Types scored per map: every registered mapped type (VA, SP, VS, ...), in registry order."""
    return mapped_types()


def resolve_points(xyz: np.ndarray, resolution: float) -> np.ndarray:
    """Cluster index of each point ``(n, 3)`` (m), in order: a point within ``resolution`` (strictly) of an earlier
    cluster's first member joins the first such cluster, any other starts one (leader clustering); ``(n,)`` int, a
    cluster numbered by its first member. Every member lies within ``resolution`` of its cluster's first one, so a
    chain of points each close to the next (facets of one facade) is not made one beyond the resolution."""
    pts = np.asarray(xyz, float).reshape(-1, 3)
    n = pts.shape[0]
    out = np.arange(n)
    if n == 0 or resolution <= 0:
        return out
    leaders: list[int] = []
    r2 = resolution * resolution
    for i in range(n):
        if leaders:
            d2 = np.sum((pts[leaders] - pts[i]) ** 2, axis=-1)
            near = np.nonzero(d2 < r2)[0]
            if near.size:
                out[i] = leaders[int(near[0])]
                continue
        leaders.append(i)
    return out


def truth_keys(paths: dict[str, np.ndarray], resolution: float = VA_KEY_RESOLUTION) -> np.ndarray:
    """Evaluation identity of each path row's landmark, ``(n,)`` str.

    A VA is its image source (the BS mirrored in a plane), so two facades of different buildings
    on one plane are one VA: rows of MIRROR-geometry types are keyed by the image position rounded
    to :data:`VA_KEY_RESOLUTION`; every other type by its ``landmark_id``. ``resolution`` (m,
    ``evaluation.va_resolution``): image sources within it of an earlier one are one VA with it, keyed by the first
    one's position (:func:`resolve_points`): the sensor cannot tell them apart.
    """
    ids = np.asarray(paths["landmark_id"]).astype(str)
    typ = np.asarray(paths["type"])
    out = ids.astype(object)
    for spec in mapped_types():
        if spec.geometry != Bounce.MIRROR:
            continue
        va = np.nonzero(typ == spec.code)[0]
        if va.size:
            xyz = np.stack([np.asarray(paths[c], float)[va] for c in ("lm_x", "lm_y", "lm_z")], -1)
            q = np.rint(xyz / VA_KEY_RESOLUTION).astype(np.int64)
            uq, first, inv = np.unique(q, axis=0, return_index=True, return_inverse=True)
            order = np.argsort(first, kind="stable")  # distinct image sources in order of appearance
            rep = order[resolve_points(uq[order] * VA_KEY_RESOLUTION, resolution)]
            q = uq[rep][np.argsort(order)][inv.reshape(-1)]
            out[va] = [f"{spec.name.lower()}@{a},{b},{c}" for a, b, c in q]
    return out.astype(str)


def _truth_rows(paths: dict[str, np.ndarray], resolution: float = VA_KEY_RESOLUTION) -> tuple[np.ndarray, ...]:
    """``step, type, rx (n,)``, evaluation keys ``(n,)`` (:func:`truth_keys`) and landmark positions ``(n, 3)``."""
    xyz = np.stack([np.asarray(paths["lm_x"], float), np.asarray(paths["lm_y"], float),
                    np.asarray(paths["lm_z"], float)], -1)
    return np.asarray(paths["step"]), np.asarray(paths["type"]), np.asarray(paths["rx"]), truth_keys(paths, resolution), xyz


def first_seen(paths: dict[str, np.ndarray], n_veh: int, steps: int, positions: np.ndarray,
               sensor: Any, resolution: float = VA_KEY_RESOLUTION) -> dict[int, list[Seen]]:
    """Static type code -> per vehicle: landmark key -> (first step it could be detected by that vehicle, position).

    A landmark counts from the first step it is in the vehicle's paths *and* inside its FOV
    (``fov_detect_prob > 0`` at the true antenna ``positions (steps, n_veh, 3)``): a ray tracer
    reports scatterers at any range, but the sensor (and so the filter) only sees them within
    ``fov_range``; a landmark the vehicle could never measure is not a missed one. ``resolution``:
    the VA resolution of :func:`truth_keys`.
    """
    from ..sim.sensor import fov_detect_prob

    static = [s.code for s in evaluated_types() if not s.moving]
    out: dict[int, list[Seen]] = {c: [{} for _ in range(n_veh)] for c in static}
    step, typ, rx, ids, xyz = _truth_rows(paths, resolution)
    sel = np.nonzero(np.isin(typ, static) & (step < steps))[0]
    if sel.size:
        u = positions[step[sel], rx[sel]]
        pd = fov_detect_prob(u, xyz[sel], typ[sel], sensor)
        sel = sel[np.asarray(pd, float) > 0]
    for i in sel[np.argsort(step[sel], kind="stable")]:
        d = out[int(typ[i])][int(rx[i])]
        if ids[i] not in d:
            d[ids[i]] = (int(step[i]), xyz[i])
    return out


def visible_counts(paths: dict[str, np.ndarray], n_veh: int, steps: int, positions: np.ndarray,
                   sensor: Any, resolution: float = VA_KEY_RESOLUTION) -> dict[int, np.ndarray]:
    """type code -> ``(steps, n_veh + 1)`` number of distinct landmarks of that type each vehicle could
    detect at each step (in its paths at that step and inside its FOV); the last column counts the
    union over vehicles (the fused map's). Tells forgetting (truth counts a landmark from its first
    sighting on) from never seeing."""
    from ..sim.sensor import fov_detect_prob

    step, typ, rx, ids, xyz = _truth_rows(paths, resolution)
    out = {}
    for spec in evaluated_types():
        t = spec.code
        sel = np.nonzero((typ == t) & (step < steps))[0]
        sets = [[set() for _ in range(n_veh + 1)] for _ in range(steps)]
        if sel.size:
            pd = np.asarray(fov_detect_prob(positions[step[sel], rx[sel]], xyz[sel], t, sensor), float)
            for i in sel[pd > 0]:
                sets[int(step[i])][int(rx[i])].add(ids[i])
                sets[int(step[i])][n_veh].add(ids[i])
        out[t] = np.array([[len(c) for c in row] for row in sets], np.int32).reshape(steps, n_veh + 1)
    return out


def sightings(paths: dict[str, np.ndarray], steps: int, positions: np.ndarray, sensor: Any,
              resolution: float = VA_KEY_RESOLUTION) -> dict[int, dict[str, set[int]]]:
    """Static type code -> landmark key -> the distinct steps ``< steps`` at which some vehicle could detect it (in
    its paths and inside its FOV at the true antenna ``positions (steps, n_veh, 3)``, m; as :func:`visible_counts`
    counts). ``resolution``: the VA resolution of :func:`truth_keys`."""
    from ..sim.sensor import fov_detect_prob

    step, typ, rx, ids, xyz = _truth_rows(paths, resolution)
    out: dict[int, dict[str, set[int]]] = {}
    for spec in evaluated_types():
        if spec.moving:
            continue
        t = spec.code
        sel = np.nonzero((typ == t) & (step < steps))[0]
        seen: dict[str, set[int]] = {}
        if sel.size:
            pd = np.asarray(fov_detect_prob(positions[step[sel], rx[sel]], xyz[sel], t, sensor), float)
            for i in sel[pd > 0]:
                seen.setdefault(str(ids[i]), set()).add(int(step[i]))
        out[t] = seen
    return out


def unconfirmed_counts(paths: dict[str, np.ndarray], n_veh: int, steps: int, positions: np.ndarray,
                       sensor: Any, resolution: float = VA_KEY_RESOLUTION, min_steps: int = 2) -> dict[int, np.ndarray]:
    """Static type code -> ``(steps,)`` number of the fused map's truth landmarks at step ``k`` (first seen at or
    before ``k`` by some vehicle, :func:`first_seen`) that some vehicle could detect at fewer than ``min_steps``
    distinct steps ``<= k`` (:func:`sightings`).

    A filter that confirms a landmark only after a second detection (a measurement-driven birth from one scan
    has a small weight) cannot have found those: a map holding every other truth exactly and none of these
    scores ``(c^p / alpha n_unconfirmed)^(1/p)``, the floor of the fused GOSPA for such a filter
    (``benchmarks/city_va.py`` prints it as ``floor2``). Arrays ``positions (steps, n_veh, 3)`` m.
    """
    if min_steps < 1:
        raise ValueError(f"min_steps={min_steps}: expected a number of detections >= 1")
    out = {}
    for t, seen in sightings(paths, steps, positions, sensor, resolution).items():
        counts = np.zeros(steps, np.int32)
        for s in seen.values():
            ordered = sorted(s)
            confirmed = ordered[min_steps - 1] if len(ordered) >= min_steps else steps
            counts[ordered[0]:confirmed] += 1  # in the truth from its first sighting, unconfirmed until then
        out[t] = counts
    return out


def all_static(paths: dict[str, np.ndarray], steps: int, resolution: float = VA_KEY_RESOLUTION) -> dict[int, Seen]:
    """type code -> every static landmark of that type in ``paths`` (steps ``< steps``, any vehicle, in
    its FOV or not), each "seen" at step 0 (``evaluation.truth_set = "all"``: every map is scored
    against the scene's whole static truth from the start, as the TWC2020 code scores). ``resolution``:
    the VA resolution of :func:`truth_keys`."""
    static = [s.code for s in evaluated_types() if not s.moving]
    out: dict[int, Seen] = {c: {} for c in static}
    step, typ, _, ids, xyz = _truth_rows(paths, resolution)
    for i in np.nonzero(np.isin(typ, static) & (step < steps))[0]:
        out[int(typ[i])].setdefault(ids[i], (0, xyz[i]))
    return out


def truth_static(seen: Seen, k: int) -> np.ndarray:
    """``(n, 3)`` positions of the landmarks first seen at or before step ``k``."""
    pts = [p for s, p in seen.values() if s <= k]
    return np.array(pts, float).reshape(-1, 3)


def truth_union(own: Seen, fused: Seen, k: int, k_fused: int) -> np.ndarray:
    """``(n, 3)`` positions of the landmarks in ``own`` first seen at or before step ``k`` and of those in ``fused``
    first seen at or before ``k_fused`` (a landmark in both counts once; ``k_fused < 0``: ``own`` alone): the truth
    of a vehicle's map at ``k`` whose last downlink of the fused map was at ``k_fused``."""
    pts = {q: p for q, (s, p) in fused.items() if s <= k_fused}
    pts.update({q: p for q, (s, p) in own.items() if s <= k})
    return np.array(list(pts.values()), float).reshape(-1, 3)


def merge_seen(per_veh: list[Seen]) -> Seen:
    """Union of the vehicles' first-seen maps (earliest step wins): the fused map's truth."""
    out: Seen = {}
    for d in per_veh:
        for key, (s, p) in d.items():
            if key not in out or s < out[key][0]:
                out[key] = (s, p)
    return out


class Table:
    """Column accumulator for the Result tables."""

    def __init__(self) -> None:
        self.cols: dict[str, list] = {}

    def add(self, **kw: Any) -> None:
        for k, v in kw.items():
            self.cols.setdefault(k, []).append(v)

    def arrays(self, dtypes: dict[str, Any]) -> dict[str, np.ndarray]:
        out = {}
        for k, dt in dtypes.items():
            vals = self.cols.get(k, [])
            out[k] = np.array(vals, dtype=object) if dt is object else np.asarray(vals, dtype=dt)
        return out


MET_DT = {"step": np.int32, "map": object, "type": object, "gospa": float, "loc": float, "missed": float,
          "false": float, "n_est": np.int32, "n_true": np.int32, "card": float,
          "n_visible": np.int32}
LM_DT = {"step": np.int32, "map": object, "type": object, "x": float, "y": float, "z": float,
         "weight": float}


class MapScorer:
    """Truth and GOSPA rows of every map of one run (the ``metrics`` and ``landmarks`` tables).

    Args:
        scn: scenario (thresholds, extraction, ``[evaluation]`` GOSPA parameters, sensor FOV).
        paths: the run's ``paths`` columns (steps ``< steps``).
        true: ``(steps, n_veh, 7)`` true vehicle states.
        names: vehicle names (the ``map`` column of per-vehicle rows; the BS map is ``"fused"``).
    """

    def __init__(self, scn: Any, paths: dict[str, np.ndarray], true: np.ndarray, names: list[str]) -> None:
        steps, n_veh = true.shape[0], true.shape[1]
        self.scn, self.true, self.names, self.n_veh = scn, true, names, n_veh
        pos = true[:steps, :, 0:3]
        res = float(scn.evaluation.va_resolution)
        if scn.evaluation.truth_set == "all":
            every = all_static(paths, steps, res)
            self.seen = {t: [every[t]] * n_veh for t in every}
        else:
            self.seen = first_seen(paths, n_veh, steps, pos, scn.sensor, res)
        self.seen_all = {t: merge_seen(v) for t, v in self.seen.items()}
        self.downlinks = [-1] * n_veh
        """per vehicle: the step of its last downlink of the fused map (-1: none yet)"""
        self.visible = visible_counts(paths, n_veh, steps, pos, scn.sensor, res)
        self.types = evaluated_types()
        self.thresholds = {s.code: s.threshold(scn) for s in self.types}
        self.metrics, self.landmarks = Table(), Table()

    def vehicle_truth(self, k: int, n: int) -> dict[int, np.ndarray]:
        """Type code -> ``(n, 3)`` true landmark positions for vehicle ``n``'s map at step ``k``."""
        ts = self.true[k, n]
        out = {}
        for spec in self.types:
            if spec.moving:
                others = np.array([self.true[k, i, 0:3] for i in range(self.n_veh) if i != n]).reshape(-1, 3)
                r = spec.fov_radius(self.scn.sensor)
                out[spec.code] = (others[np.linalg.norm(others - ts[0:3], axis=1) <= r] if len(others)
                                  else np.zeros((0, 3)))
            else:
                out[spec.code] = truth_union(self.seen[spec.code][n], self.seen_all[spec.code], k,
                                             self.downlinks[n])
        return out

    def record_downlink(self, n: int, k: int) -> None:
        """Vehicle ``n`` received the fused map at step ``k`` (after its row of step ``k``): from step ``k + 1`` on its
        maps' truth holds every landmark some vehicle could have detected by ``k`` (:func:`truth_union`)."""
        self.downlinks[n] = int(k)

    def fused_truth(self, k: int) -> dict[int, np.ndarray]:
        """Type code -> ``(n, 3)`` true positions for the BS map at step ``k`` (all vehicles for moving types)."""
        return {s.code: (self.true[k, :, 0:3].copy() if s.moving else truth_static(self.seen_all[s.code], k))
                for s in self.types}

    def others_truth(self, k: int, spec: LandmarkSpec) -> np.ndarray:
        """``(n, 3)`` true positions of the vehicles that some *other* vehicle could see as a VS of type
        ``spec`` at step ``k`` (within its FOV radius): the truth of the fused map's other-vehicle part."""
        pos = self.true[k, :, 0:3]
        d = np.linalg.norm(pos[:, None, :] - pos[None, :, :], axis=-1)
        np.fill_diagonal(d, np.inf)
        return pos[np.any(d <= spec.fov_radius(self.scn.sensor), axis=1)].reshape(-1, 3)

    def record_others(self, k: int, maps: dict[int, GM]) -> None:
        """Rows of map ``"fused_others"`` for the moving types (VS): the fused map's Gaussians that are not a
        vehicle's own upload (no :func:`~mmslam.slam.core.gm.ego_label`: :func:`~mmslam.slam.core.gm.is_ego_label`), scored against
        :meth:`others_truth`: VS mapping of other vehicles, apart from the ego Gaussians of eq. (11).
        Needs labels (``fusion.average_by_label``); nothing is recorded without them."""
        from ..core.gm import is_ego_label

        for spec in self.types:
            g = maps.get(spec.code)
            if not spec.moving or g is None or g.label is None:
                continue
            keep = g.mask & ~is_ego_label(g.label)
            self._score(k, "fused_others", spec, GM(g.w, g.m, g.P, keep, g.pd_beta, g.label),
                        self.others_truth(k, spec), self.n_veh)

    def record(self, k: int, name: str, maps: dict[int, GM], truth: dict[int, np.ndarray], col: int) -> None:
        """Score ``maps`` (type code -> averaged map; absent types: no estimates) of map ``name`` at step ``k``;
        ``col``: the vehicle index (``n_veh`` for the fused map) of the visible counts."""
        for spec in self.types:
            self._score(k, name, spec, maps.get(spec.code), truth[spec.code], col)

    def _score(self, k: int, name: str, spec: LandmarkSpec, g: GM | None, Y: np.ndarray, col: int) -> None:
        """One metrics row (and its landmark rows) of map ``name``, type ``spec``: estimates of ``g`` (None:
        none) against the truth ``Y (n, 3)``."""
        from .gospa import gospa

        ev, fp = self.scn.evaluation, self.scn.filter
        t = spec.code
        if g is not None:
            X, wts = estimates_of(g, self.thresholds[t], fp.extraction)
            card = cardinality(g)
        else:
            X, wts, card = np.zeros((0, 3)), np.zeros(0), 0.0
        d = gospa(Y, X, ev.gospa_c, ev.gospa_p, ev.gospa_alpha)  # (truth, estimates)
        self.metrics.add(step=k, map=name, type=spec.name, gospa=float(d.d), loc=float(d.loc),
                         missed=float(d.missed), false=float(d.false), n_est=len(X), n_true=len(Y), card=card,
                         n_visible=int(self.visible[t][k, col]))
        for x, wv in zip(X, wts):
            self.landmarks.add(step=k, map=name, type=spec.name, x=x[0], y=x[1], z=x[2], weight=float(wv))

