"""Ground-truth landmarks derived from a scenario (global frame, metres).

- VA: the BS mirrored in every building face plane whose outward side faces the BS (the wall
  can reflect BS signals), and in the ground plane if present. Id ``<object>:<face>`` with
  face in ``+x, -x, +y, -y, +z, -z``; the ground is ``ground:+z``.
- SP: each scatterer's reference point, id = its name.
- VS: the other vehicles' antenna positions per step (see :func:`vs_truth`).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mmslam.scenes.scenario import Building, Scenario
from mmslam.model import mirror_point

FACES = {"+x": (0, 1.0), "-x": (0, -1.0), "+y": (1, 1.0), "-y": (1, -1.0), "+z": (2, 1.0), "-z": (2, -1.0)}


@dataclass(frozen=True)
class Face:
    """A planar face: ``object`` name, ``face`` tag, a point on the plane and the outward normal."""

    object: str
    face: str
    point: np.ndarray
    normal: np.ndarray
    lo: np.ndarray  # face rectangle bounds (3,), lo == hi on the normal axis
    hi: np.ndarray

    @property
    def id(self) -> str:
        return f"{self.object}:{self.face}"


def building_faces(b: Building) -> list[Face]:
    """The six faces of a box building with outward normals."""
    lo, hi = np.asarray(b.min, float), np.asarray(b.max, float)
    out = []
    for tag, (ax, sgn) in FACES.items():
        n = np.zeros(3)
        n[ax] = sgn
        p = (hi if sgn > 0 else lo).copy()
        flo, fhi = lo.copy(), hi.copy()
        flo[ax] = fhi[ax] = p[ax]
        out.append(Face(b.name, tag, p, n, flo, fhi))
    return out


def reflecting_faces(scn: Scenario) -> list[Face]:
    """Faces that can specularly reflect the BS: outward normal pointing at the BS side."""
    b = scn.bs_array
    faces = []
    for bld in scn.buildings:
        for f in building_faces(bld):
            if np.dot(b - f.point, f.normal) > 1e-9:
                faces.append(f)
    if scn.ground is not None:
        e = scn.ground.extent / 2
        faces.append(Face("ground", "+z", np.array([0.0, 0.0, scn.ground.z]), np.array([0.0, 0.0, 1.0]),
                          np.array([-e, -e, scn.ground.z]), np.array([e, e, scn.ground.z])))
    return faces


def va_truth(scn: Scenario) -> dict[str, np.ndarray]:
    """VA id -> image source position ``(3,)`` (BS mirrored in the face plane)."""
    b = scn.bs_array
    return {f.id: mirror_point(b, f.point, f.normal) for f in reflecting_faces(scn)}


def sp_truth(scn: Scenario) -> dict[str, np.ndarray]:
    """SP id (scatterer name) -> reference point ``(3,)``."""
    return {s.name: np.asarray(s.position, float) for s in scn.scatterers}


def vs_truth(states: np.ndarray, names: list[str]) -> dict[str, np.ndarray]:
    """VS id (vehicle name) -> antenna positions per step ``(steps, 3)`` from ``(steps, n, 7)``."""
    return {n: states[:, i, 0:3] for i, n in enumerate(names)}
