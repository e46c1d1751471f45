"""The object set: the deterministic built-in objects and user mesh loading. Its one home.

Pure numpy + scipy (trimesh only, and lazily, to read user mesh files). No MuJoCo, no torch: the
scene builder turns each :class:`ObjectAsset`'s convex ``parts`` into MuJoCo mesh geoms, and the
observation code samples ``surface_points`` / ``surface_normals``.

Conventions (all lengths in metres, float64 geometry unless stated):

* **Object frame.** Origin at the volume centroid (the centre of mass at uniform density). Every
  built-in object is generated in a resting pose: z up, flat or round side down (mugs and bottles
  upright, prisms lying on a flat face, capsules lying along x).
* **Collision = convex parts.** MuJoCo collides every mesh geom as its convex hull, so a concave
  shape is stored as several convex pieces (a mug is a base disc, a ring of wall segments and three
  handle bars). Each part is exactly the convex hull of its vertices: ``parts[i]`` (V, 3) are the
  hull's vertices and ``part_faces[i]`` (F, 3) its outward-wound triangles. Parts touch but do not
  (or only marginally) overlap, so the volume centroid is the volume-weighted mean of part centroids.
* **Surface samples.** ``surface_points`` (2048, 3) float32 are uniform samples of the *outer*
  surface: area-weighted samples of all part hulls, minus those lying inside (or within 0.5 mm of)
  another part of the same object, which removes the faces where parts touch. ``surface_normals``
  are the outward unit normals of the sampled hull faces.
* **Determinism.** Each built-in object's dimensions and samples come from a random generator seeded
  by the CRC-32 of its name, so a name always means the same geometry, run to run and machine to
  machine.

Built-in set (``builtin_objects()``, 53 objects, sized like HACMan's: largest extent 6-12 cm, smallest
extent at least 2 cm so a 2 cm fingertip can push them):

========================= ===================================================================
split                     categories (instances)
========================= ===================================================================
``train`` (33)            box (``cube`` + ``box_00..03``), cylinder, bottle, mug, bowl, l_prism,
                          t_prism, capsule (``_00..03`` each)
``unseen-instance`` (8)   one new instance (``_04``) of each training category
``unseen-category`` (12)  torus, u_prism, cone (frustum), hex_prism, cross, wedge (``_00..01`` each)
========================= ===================================================================

``train-extra`` (64, built on first use by :func:`extra_train_objects`, not in ``all``): instances
``_05..12`` of each training category, for training on more shapes of the same categories
(``--objects train-wide`` = ``train`` + ``train-extra``); no category is added, so the unseen splits
stay unseen. ``train-varied`` (:func:`varied_train_objects`, not in ``all``): 16 irregular convex
``polyhedron`` and 16 stepped multi-box ``blocks`` bodies, categories of their own that no evaluated
split holds (``--objects train-varied`` = ``train-wide`` + these): more kinds of shape for a policy
meant for meshes a user brings.

The special spec ``cube`` is a 6 cm cube named ``cube``; it **is also part of** ``train`` (category
``box``), so a policy trained on ``train`` has seen it.

The built-in shapes are convex hulls of small, explicitly generated point sets (rings, boxes,
hemispheres) rather than ``trimesh.creation`` meshes: that is the same geometry, but it keeps the
built-in path free of trimesh's ~1 s import and makes each part's vertex count explicit (≤ 64).
"""

from __future__ import annotations

import functools
import hashlib
import os
import zlib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial import ConvexHull, QhullError

SPLITS = ("train", "unseen-instance", "unseen-category")
#: ``train-extra``: more instances of the training categories, for training only (never evaluated
#: as a split of Table I); ``train-wide``: ``train`` and ``train-extra`` together.
EXTRA_SPLIT = "train-extra"
#: ``train-varied``: ``train-wide`` plus ``VARIED_CATEGORIES`` (split ``train-varied``), training only.
VARIED_SPLIT = "train-varied"
SPEC_CHOICES = (
    "train",
    "unseen-instance",
    "unseen-category",
    "unseen",
    "all",
    "cube",
    EXTRA_SPLIT,
    "train-wide",
    "train-varied",
)

N_SURFACE_SAMPLES = 2048  # surface samples per object
INSIDE_TOL_M = 0.0005  # a sample this close to (or inside) another part is not on the outer surface
MESH_SUFFIXES = (".obj", ".stl")  # user mesh formats load_objects picks up from a folder
USER_MIN_EXTENT_M = 0.02  # a user mesh whose largest extent is below this is refused
USER_MAX_EXTENT_M = 0.30  # ... or above this
USER_MAX_HULL_VERTICES = 128  # a user mesh's collision hull is thinned to at most this many vertices
USER_MAX_PARTS = 16  # a user mesh of more separate pieces than this collides as one hull


class ObjectMeshError(ValueError):
    """A user mesh (or folder) that cannot be used; the one-line message names the file and why."""


@dataclass(frozen=True, eq=False)
class ObjectAsset:
    """One object: convex collision parts plus outer-surface samples, all in the object frame (metres).

    ``eq=False``: assets compare by identity (array fields have no useful ``==``). The arrays of
    built-in assets are read-only because ``builtin_objects()`` hands out one cached copy.
    """

    name: str  # stable, e.g. "mug_02"; the file stem for user meshes
    category: str  # e.g. "mug"; "user" for user meshes
    split: str  # "train" | "unseen-instance" | "unseen-category" | "user"
    parts: tuple[np.ndarray, ...]  # convex parts, each (V, 3) float64 hull vertices
    part_faces: tuple[np.ndarray, ...]  # each (F, 3) int64 outward-wound triangles into that part
    surface_points: np.ndarray  # (N_SURFACE_SAMPLES, 3) float32 uniform outer-surface samples
    surface_normals: np.ndarray  # (N_SURFACE_SAMPLES, 3) float32 outward unit normals
    extents: np.ndarray  # (3,) float64 axis-aligned bounding-box size of the parts


# --------------------------------------------------------------------------------------------------
# Convex hull utilities (shared by built-in and user objects)
# --------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Hull:
    vertices: np.ndarray  # (V, 3) hull vertices
    faces: np.ndarray  # (F, 3) outward-wound triangles into ``vertices``
    equations: np.ndarray  # (F, 4) outward unit normal n and offset d per face: n·p + d <= 0 inside
    volume: float
    centroid: np.ndarray  # (3,) volume centroid


def _hull(points: np.ndarray) -> _Hull:
    """Convex hull of points (P, 3) keeping only its vertices, with outward-wound faces."""
    h = ConvexHull(np.asarray(points, dtype=np.float64))
    keep = np.sort(h.vertices)  # sorted so the output order never depends on Qhull's internals
    remap = np.full(len(h.points), -1, dtype=np.int64)
    remap[keep] = np.arange(len(keep))
    verts = h.points[keep]
    faces = remap[h.simplices]
    eq = h.equations
    # Qhull's triangles have arbitrary winding; flip those whose winding normal disagrees with the
    # (always outward) facet equation so renderers and trimesh see a consistently outward mesh.
    a, b, c = verts[faces[:, 0]], verts[faces[:, 1]], verts[faces[:, 2]]
    flip = np.einsum("ij,ij->i", np.cross(b - a, c - a), eq[:, :3]) < 0
    faces[flip] = faces[flip][:, ::-1]
    # Volume centroid: sum of tetrahedra from an interior point (the vertex mean) to every face.
    o = verts.mean(axis=0)
    a, b, c = verts[faces[:, 0]], verts[faces[:, 1]], verts[faces[:, 2]]
    tet_vol = np.einsum("ij,ij->i", a - o, np.cross(b - o, c - o)) / 6.0
    vol = float(tet_vol.sum())
    centroid = (tet_vol[:, None] * (a + b + c + o)).sum(axis=0) / (4.0 * vol)
    return _Hull(verts, faces, eq, vol, centroid)


def _max_plane_distance(points: np.ndarray, equations: np.ndarray) -> np.ndarray:
    """Signed distance (M,) of points (M, 3) to a convex hull's boundary: ≤ 0 inside, > 0 outside
    (exact outside along face normals, a lower bound near edges, which is all the tests need)."""
    return (points @ equations[:, :3].T + equations[:, 3]).max(axis=1)


def _sample_triangles(
    tri: np.ndarray, tri_normals: np.ndarray, count: int, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Area-weighted uniform samples on triangles (T, 3, 3): returns points (count, 3), their
    triangle's unit normals (count, 3) and the triangle indices (count,)."""
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    idx = rng.choice(len(tri), size=count, p=area / area.sum())
    u, v = rng.random(count), rng.random(count)
    fold = u + v > 1.0  # reflect into the triangle: keeps the distribution uniform
    u[fold], v[fold] = 1.0 - u[fold], 1.0 - v[fold]
    t = tri[idx]
    pts = t[:, 0] + u[:, None] * (t[:, 1] - t[:, 0]) + v[:, None] * (t[:, 2] - t[:, 0])
    return pts, tri_normals[idx], idx


def _outer_surface_samples(
    hulls: list[_Hull], rng: np.random.Generator, count: int = N_SURFACE_SAMPLES
) -> tuple[np.ndarray, np.ndarray]:
    """Uniform samples (count, 3) of the outer surface of a union of convex hulls, and their outward
    unit normals (count, 3): sample all hull faces by area, drop samples inside (or within
    ``INSIDE_TOL_M`` of) a *different* hull, and top up until exactly ``count`` remain."""
    tri = np.concatenate([h.vertices[h.faces] for h in hulls])
    normals = np.concatenate([h.equations[:, :3] for h in hulls])
    owner = np.concatenate([np.full(len(h.faces), i) for i, h in enumerate(hulls)])
    got_p, got_n, have = [], [], 0
    for _ in range(50):  # in practice one or two rounds; the cap only guards against a bug
        pts, nrm, idx = _sample_triangles(tri, normals, 2 * count, rng)
        keep = np.ones(len(pts), dtype=bool)
        if len(hulls) > 1:
            for j, h in enumerate(hulls):
                other = owner[idx] != j
                keep &= ~(other & (_max_plane_distance(pts, h.equations) < INSIDE_TOL_M))
        take = min(count - have, int(keep.sum()))
        got_p.append(pts[keep][:take])
        got_n.append(nrm[keep][:take])
        have += take
        if have == count:
            break
    else:
        raise RuntimeError("outer surface sampling did not converge (parts fully inside each other?)")
    return np.concatenate(got_p), np.concatenate(got_n)


def _readonly(a: np.ndarray) -> np.ndarray:
    a.flags.writeable = False
    return a


# --------------------------------------------------------------------------------------------------
# Point-set generators for convex parts (each returns (P, 3) points whose hull is the part)
# --------------------------------------------------------------------------------------------------


def _box(lo, hi) -> np.ndarray:
    """The 8 corners of the axis-aligned box [lo, hi] (each (3,), metres)."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    c = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], dtype=float)
    return lo + c * (hi - lo)


def _rings(rz: list[tuple[float, float]], sections: int, phase: float = 0.0) -> np.ndarray:
    """Rings of ``sections`` points about the z axis at (radius, z) pairs: the convex hull is a
    solid of revolution (polygonal), convex when r(z) is concave along the list. Radius 0 is a point."""
    ang = phase + 2 * np.pi * np.arange(sections) / sections
    out = []
    for r, z in rz:
        if r <= 0:
            out.append([[0.0, 0.0, z]])
        else:
            out.append(np.stack([r * np.cos(ang), r * np.sin(ang), np.full(sections, z)], axis=1))
    return np.concatenate(out)


def _wall_segment(th0, th1, z0, z1, rin0, rout0, rin1, rout1, n_outer) -> np.ndarray:
    """One convex piece of a thin wall of revolution between angles th0..th1 (radians) and heights
    z0..z1: outer face on ``n_outer`` points of the arc (radius rout0 at z0, rout1 at z1), inner
    face flat on the chord (radius rin0 / rin1). Adjacent segments share their radial faces."""
    ang_o = np.linspace(th0, th1, n_outer)
    ang_i = np.array([th0, th1])
    pts = []
    for z, rin, rout in ((z0, rin0, rout0), (z1, rin1, rout1)):
        pts.append(np.stack([rout * np.cos(ang_o), rout * np.sin(ang_o), np.full(n_outer, z)], 1))
        pts.append(np.stack([rin * np.cos(ang_i), rin * np.sin(ang_i), np.full(2, z)], 1))
    return np.concatenate(pts)


# --------------------------------------------------------------------------------------------------
# Category generators: rng -> list of convex point sets (metres, resting pose, any origin)
# --------------------------------------------------------------------------------------------------


def _gen_box(rng: np.random.Generator) -> list[np.ndarray]:
    ext = [rng.uniform(0.07, 0.12), rng.uniform(0.03, 0.08), rng.uniform(0.025, 0.06)]
    return [_box([0, 0, 0], ext)]


def _gen_cylinder(rng):  # upright
    r, h = rng.uniform(0.015, 0.04), rng.uniform(0.07, 0.12)
    return [_rings([(r, 0.0), (r, h)], 24)]


def _gen_bottle(rng):  # upright: body with a rounded shoulder (one convex part) + neck
    rb, rn = rng.uniform(0.02, 0.035), rng.uniform(0.009, 0.012)
    hb, hs, hn = rng.uniform(0.045, 0.065), rng.uniform(0.015, 0.025), rng.uniform(0.015, 0.025)
    # r(z) constant, then a concave (bulging) shoulder: the body + shoulder stays convex. The neck
    # turns the profile back to vertical, so it must be its own part.
    rmid = rn + 0.7 * (rb - rn)
    body = _rings([(rb, 0.0), (rb, hb), (rmid, hb + 0.5 * hs), (rn, hb + hs)], 16)
    neck = _rings([(rn, hb + hs), (rn, hb + hs + hn)], 16)
    return [body, neck]


def _gen_mug(rng):  # upright, handle towards +x
    R, t = rng.uniform(0.03, 0.04), rng.uniform(0.004, 0.006)
    H, tb = rng.uniform(0.07, 0.10), rng.uniform(0.005, 0.008)
    hx = rng.uniform(0.018, 0.028)  # how far the handle sticks out from the wall
    n_seg, n_outer = 8, 4
    step = 2 * np.pi / n_seg
    th0 = -step / 2  # a segment is centred on +x, so the handle meets a nearly flat outer face
    # Base disc uses the walls' outer polygon (n_seg*(n_outer-1) unique angles) so they line up.
    base = _rings([(R, 0.0), (R, tb)], n_seg * (n_outer - 1), phase=th0)
    walls = [
        _wall_segment(th0 + k * step, th0 + (k + 1) * step, tb, H, R - t, R, R - t, R, n_outer)
        for k in range(n_seg)
    ]
    bar, by = 0.008, 0.012  # handle bar thickness and width
    zlo, zhi = 0.25 * H, 0.8 * H
    x0, x1 = R - t / 2, R + hx  # bars start inside the wall (never reaching the cavity)
    handle = [
        _box([x1 - bar, -by / 2, zlo], [x1, by / 2, zhi]),  # vertical grip
        _box([x0, -by / 2, zhi - bar], [x1 - bar, by / 2, zhi]),  # top bar
        _box([x0, -by / 2, zlo], [x1 - bar, by / 2, zlo + bar]),  # bottom bar
    ]
    return [base, *walls, *handle]


def _gen_bowl(rng):  # upright, flaring wall
    rb, rt = rng.uniform(0.025, 0.035), rng.uniform(0.045, 0.055)
    H, tb, t = rng.uniform(0.035, 0.05), 0.006, 0.005
    n_seg, n_outer = 10, 3
    step = 2 * np.pi / n_seg
    r_at = lambda z: rb + (rt - rb) * z / H  # noqa: E731 - outer radius along the height
    base = _rings([(rb, 0.0), (r_at(tb), tb)], n_seg * (n_outer - 1))
    walls = [
        _wall_segment(k * step, (k + 1) * step, tb, H, r_at(tb) - t, r_at(tb), rt - t, rt, n_outer)
        for k in range(n_seg)
    ]
    return [base, *walls]


def _gen_l_prism(rng):  # lying flat, thickness along z
    T, a, b = rng.uniform(0.025, 0.04), rng.uniform(0.08, 0.12), rng.uniform(0.055, 0.09)
    w1, w2 = rng.uniform(0.025, 0.035), rng.uniform(0.025, 0.035)
    return [_box([0, 0, 0], [a, w1, T]), _box([0, w1, 0], [w2, b, T])]


def _gen_t_prism(rng):
    T, a, s = rng.uniform(0.025, 0.04), rng.uniform(0.08, 0.12), rng.uniform(0.04, 0.075)
    w1, w2 = rng.uniform(0.025, 0.035), rng.uniform(0.025, 0.035)
    return [_box([-a / 2, 0, 0], [a / 2, w1, T]), _box([-w2 / 2, -s, 0], [w2 / 2, 0, T])]


def _gen_capsule(rng):  # lying along x
    r, L = rng.uniform(0.012, 0.025), rng.uniform(0.08, 0.12)
    half = L / 2 - r  # half length of the cylindrical middle
    ang = 2 * np.pi * np.arange(10) / 10
    pts = []
    for sgn in (-1.0, 1.0):  # two hemispheres: rings at 0, 40 and 70 degrees elevation + pole
        for elev in np.radians([0.0, 40.0, 70.0]):
            rr = r * np.cos(elev)
            x = sgn * (half + r * np.sin(elev))
            pts.append(np.stack([np.full(10, x), rr * np.cos(ang), rr * np.sin(ang)], 1))
        pts.append([[sgn * (half + r), 0.0, 0.0]])
    return [np.concatenate(pts)]  # 62 vertices


def _gen_torus(rng):  # lying flat: a ring of convex segments, each the hull of two cross-sections
    R, r = rng.uniform(0.035, 0.045), rng.uniform(0.010, 0.014)
    n_seg, n_circ = 12, 10
    phi = 2 * np.pi * np.arange(n_circ) / n_circ

    def section(th):
        rho = R + r * np.cos(phi)
        return np.stack([rho * np.cos(th), rho * np.sin(th), r * np.sin(phi)], 1)

    return [
        np.concatenate([section(2 * np.pi * k / n_seg), section(2 * np.pi * (k + 1) / n_seg)])
        for k in range(n_seg)
    ]


def _gen_u_prism(rng):  # lying flat: a base bar and two arms
    T, a, b = rng.uniform(0.025, 0.04), rng.uniform(0.08, 0.11), rng.uniform(0.06, 0.09)
    w, w2 = rng.uniform(0.02, 0.03), rng.uniform(0.02, 0.028)
    return [
        _box([-a / 2, 0, 0], [a / 2, w, T]),
        _box([-a / 2, w, 0], [-a / 2 + w2, b, T]),
        _box([a / 2 - w2, w, 0], [a / 2, b, T]),
    ]


def _gen_cone(rng):  # upright frustum (a sharp apex would be unpushable and unstable)
    r0, r1, h = rng.uniform(0.035, 0.045), rng.uniform(0.01, 0.02), rng.uniform(0.06, 0.09)
    return [_rings([(r0, 0.0), (r1, h)], 24)]


def _gen_hex_prism(rng):  # upright
    rc, h = rng.uniform(0.03, 0.045), rng.uniform(0.03, 0.10)
    return [_rings([(rc, 0.0), (rc, h)], 6)]


def _gen_cross(rng):  # lying flat: a plus sign from a long bar and two short arms
    T, a, b = rng.uniform(0.025, 0.035), rng.uniform(0.08, 0.11), rng.uniform(0.07, 0.10)
    w, w2 = rng.uniform(0.022, 0.03), rng.uniform(0.022, 0.03)
    return [
        _box([-a / 2, -w / 2, 0], [a / 2, w / 2, T]),
        _box([-w2 / 2, w / 2, 0], [w2 / 2, b / 2, T]),
        _box([-w2 / 2, -b / 2, 0], [w2 / 2, -w / 2, T]),
    ]


def _gen_wedge(rng):  # a triangular prism resting on its long rectangular face
    L, W, h = rng.uniform(0.08, 0.11), rng.uniform(0.04, 0.07), rng.uniform(0.03, 0.055)
    tri = np.array([[0.0, 0.0], [L, 0.0], [0.0, h]])  # (x, z) profile
    return [np.array([[x, y, z] for y in (0.0, W) for x, z in tri])]


def _gen_polyhedron(rng):  # an irregular convex body: the hull of 10-24 points on a dented, stretched shell
    n = int(rng.integers(10, 25))
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    p = d * rng.uniform(0.75, 1.0, (n, 1)) * rng.uniform(0.5, 1.0, 3)
    return [p * rng.uniform(0.065, 0.11) / np.ptp(p, axis=0).max()]  # largest extent 6.5-11 cm


def _gen_blocks(rng):  # 2-3 boxes of random proportions, each on a face of the one before: steps, Ls, Ts
    lo, hi = np.zeros(3), rng.uniform([0.04, 0.03, 0.02], [0.09, 0.07, 0.05])
    parts = [_box(lo, hi)]
    for _ in range(int(rng.integers(1, 3))):
        axis, up = int(rng.integers(3)), bool(rng.integers(2))  # the face of the last box to build on
        size = rng.uniform(0.02, 0.05, 3)
        new_lo = np.empty(3)
        for k in range(3):
            if k == axis:
                new_lo[k] = hi[k] if up else lo[k] - size[k]
            else:  # anywhere along the face that keeps at least 1 cm of contact
                new_lo[k] = rng.uniform(lo[k] - size[k] + 0.01, hi[k] - 0.01)
        lo, hi = new_lo, new_lo + size
        parts.append(_box(lo, hi))
    return parts


_Generator = Callable[[np.random.Generator], list[np.ndarray]]

#: Training categories: instances _00.._03 are ``train``, _04 is ``unseen-instance``.
TRAIN_CATEGORIES: dict[str, _Generator] = {
    "box": _gen_box,
    "cylinder": _gen_cylinder,
    "bottle": _gen_bottle,
    "mug": _gen_mug,
    "bowl": _gen_bowl,
    "l_prism": _gen_l_prism,
    "t_prism": _gen_t_prism,
    "capsule": _gen_capsule,
}
#: Categories never seen in training: instances _00.._01 are ``unseen-category``.
UNSEEN_CATEGORIES: dict[str, _Generator] = {
    "torus": _gen_torus,
    "u_prism": _gen_u_prism,
    "cone": _gen_cone,
    "hex_prism": _gen_hex_prism,
    "cross": _gen_cross,
    "wedge": _gen_wedge,
}
#: Shapes outside the evaluated categories, for training only (``train-varied``): irregular convex
#: bodies and stepped multi-box bodies, so that a policy sees more than the eight regular families.
VARIED_CATEGORIES: dict[str, _Generator] = {"polyhedron": _gen_polyhedron, "blocks": _gen_blocks}
N_VARIED_INSTANCES = 16
N_TRAIN_INSTANCES, N_UNSEEN_INSTANCES, N_UNSEEN_CATEGORY_INSTANCES = 4, 1, 2
#: ``train-extra`` instances per training category: ``_05`` onwards (``_04`` stays unseen-instance).
N_EXTRA_TRAIN_INSTANCES = 8
CUBE_SIZE_M = 0.06


def _seed(name: str) -> int:
    # zlib.crc32, not hash(): Python randomises str hashes per process.
    return zlib.crc32(name.encode("utf-8"))


def _make_asset(name: str, category: str, split: str, point_sets: list[np.ndarray]) -> ObjectAsset:
    """Centre convex point sets at their joint volume centroid and sample the outer surface."""
    hulls = [_hull(p) for p in point_sets]
    vol = np.array([h.volume for h in hulls])
    centre = (vol[:, None] * np.stack([h.centroid for h in hulls])).sum(0) / vol.sum()
    hulls = [_hull(h.vertices - centre) for h in hulls]  # re-hull: equations follow the shift
    pts, nrm = _outer_surface_samples(hulls, np.random.default_rng([_seed(name), 1]))
    allv = np.concatenate([h.vertices for h in hulls])
    return ObjectAsset(
        name=name,
        category=category,
        split=split,
        parts=tuple(_readonly(h.vertices) for h in hulls),
        part_faces=tuple(_readonly(h.faces) for h in hulls),
        surface_points=_readonly(pts.astype(np.float32)),
        surface_normals=_readonly(nrm.astype(np.float32)),
        extents=_readonly(allv.max(0) - allv.min(0)),
    )


def geometry_hash(asset: ObjectAsset) -> str:
    """Short sha256 of an object's collision parts: the key of every per-object cache (stable poses,
    symmetries)."""
    h = hashlib.sha256()
    for p in asset.parts:
        h.update(np.ascontiguousarray(p, dtype=np.float64).tobytes())
    return h.hexdigest()[:16]


def cache_root() -> Path:
    """Where per-object results computed on first use are cached (``HYDO_CACHE``, default
    ``~/.cache/hydo``)."""
    return Path(os.environ.get("HYDO_CACHE", Path.home() / ".cache" / "hydo"))


@functools.cache
def builtin_objects() -> tuple[ObjectAsset, ...]:
    """All built-in objects (see the module docstring for splits), built once and cached.

    Returns a tuple of :class:`ObjectAsset` (metres, object frame) in a fixed order: ``cube``, then
    the training categories' instances, then the unseen categories'. Takes well under 2 s; call
    ``builtin_objects.cache_clear()`` to force a rebuild.
    """
    specs: list[tuple[str, str, str, _Generator]] = [
        ("cube", "box", "train", lambda rng: [_box([0, 0, 0], [CUBE_SIZE_M] * 3)])
    ]
    for cat, gen in TRAIN_CATEGORIES.items():
        for i in range(N_TRAIN_INSTANCES + N_UNSEEN_INSTANCES):
            split = "train" if i < N_TRAIN_INSTANCES else "unseen-instance"
            specs.append((f"{cat}_{i:02d}", cat, split, gen))
    for cat, gen in UNSEEN_CATEGORIES.items():
        for i in range(N_UNSEEN_CATEGORY_INSTANCES):
            specs.append((f"{cat}_{i:02d}", cat, "unseen-category", gen))
    return tuple(
        _make_asset(name, cat, split, gen(np.random.default_rng([_seed(name), 0])))
        for name, cat, split, gen in specs
    )


@functools.cache
def extra_train_objects() -> tuple[ObjectAsset, ...]:
    """The ``train-extra`` split: instances ``_05`` .. ``_12`` of every training category (64
    objects), from the same generators and name seeds as the built-in set. Built on first use only
    (about as long again as :func:`builtin_objects`), so commands that never ask for them do not pay
    for them. Not part of ``all``: ``all`` is the evaluated set."""
    first = N_TRAIN_INSTANCES + N_UNSEEN_INSTANCES
    names = [
        (f"{cat}_{i:02d}", cat, gen)
        for cat, gen in TRAIN_CATEGORIES.items()
        for i in range(first, first + N_EXTRA_TRAIN_INSTANCES)
    ]
    return tuple(
        _make_asset(name, cat, EXTRA_SPLIT, gen(np.random.default_rng([_seed(name), 0])))
        for name, cat, gen in names
    )


@functools.cache
def varied_train_objects() -> tuple[ObjectAsset, ...]:
    """The shapes of ``VARIED_CATEGORIES`` (``N_VARIED_INSTANCES`` of each, split ``train-varied``),
    built on first use; never in ``all`` or an evaluated split, so nothing evaluated is trained on."""
    return tuple(
        _make_asset(name, cat, VARIED_SPLIT, gen(np.random.default_rng([_seed(name), 0])))
        for cat, gen in VARIED_CATEGORIES.items()
        for name in (f"{cat}_{i:02d}" for i in range(N_VARIED_INSTANCES))
    )


def _is_extra_name(s: str) -> bool:
    cat, _, num = s.rpartition("_")
    first = N_TRAIN_INSTANCES + N_UNSEEN_INSTANCES
    return cat in TRAIN_CATEGORIES and num.isdigit() and first <= int(num) < first + N_EXTRA_TRAIN_INSTANCES


def load_objects(spec: str | Path) -> tuple[ObjectAsset, ...]:
    """Objects for a spec; returns a non-empty tuple of :class:`ObjectAsset` (metres, object frame).

    ``spec`` is one of ``SPEC_CHOICES`` (``unseen`` is both unseen splits, ``all`` every built-in
    object, ``cube`` the single 6 cm cube, ``train-extra`` / ``train-wide`` the extra training
    instances alone / with ``train``: :func:`extra_train_objects`), a built-in object name such as ``"mug_02"``, or a path
    to a ``.obj`` / ``.stl`` file or to a folder whose ``.obj`` / ``.stl`` files (not sub-folders)
    are loaded in name order with :func:`load_user_mesh`. Raises ``ObjectMeshError`` for a bad mesh
    or a folder without meshes, and ``ValueError`` for a spec that is none of these.
    """
    objs = builtin_objects()
    s = str(spec)
    if s in SPLITS:
        return tuple(o for o in objs if o.split == s)
    if s == "unseen":
        return tuple(o for o in objs if o.split in ("unseen-instance", "unseen-category"))
    if s == "all":
        return objs
    if s == EXTRA_SPLIT:
        return extra_train_objects()
    if s == "train-wide":
        return tuple(o for o in objs if o.split == "train") + extra_train_objects()
    if s == VARIED_SPLIT:
        return load_objects("train-wide") + varied_train_objects()
    by_name = {o.name: o for o in objs}  # includes "cube"
    if s in by_name:
        return (by_name[s],)
    if _is_extra_name(s):
        return tuple(o for o in extra_train_objects() if o.name == s)
    if s.rpartition("_")[0] in VARIED_CATEGORIES:
        if found := tuple(o for o in varied_train_objects() if o.name == s):
            return found
    path = Path(spec)
    if path.is_dir():
        files = sorted(p for p in path.iterdir() if p.is_file() and p.suffix.lower() in MESH_SUFFIXES)
        if not files:
            raise ObjectMeshError(f"{path}: folder contains no .obj or .stl files")
        assets = [load_user_mesh(p) for p in files]
        # Two files with the same stem (a.obj, a.stl) would share a name; keep the file name then.
        stems = [a.name for a in assets]
        return tuple(
            a if stems.count(a.name) == 1 else _renamed(a, f.name) for a, f in zip(assets, files, strict=True)
        )
    if path.suffix.lower() in MESH_SUFFIXES or path.exists():
        return (load_user_mesh(path),)
    raise ValueError(
        f"unknown object spec '{s}': expected one of {', '.join(SPEC_CHOICES)}, a built-in object name "
        "(e.g. mug_02), or a path to a .obj/.stl file or a folder of them"
    )


def _renamed(a: ObjectAsset, name: str) -> ObjectAsset:
    return ObjectAsset(
        name, a.category, a.split, a.parts, a.part_faces, a.surface_points, a.surface_normals, a.extents
    )


# --------------------------------------------------------------------------------------------------
# User meshes
# --------------------------------------------------------------------------------------------------


def _one_line(exc: BaseException) -> str:
    return f"{type(exc).__name__}: {' '.join(str(exc).split())}"


def _check_stl_bytes(path: Path, err: Callable[[str], ObjectMeshError]) -> None:
    """Refuse files that are neither ASCII STL nor a binary STL of consistent length, before trimesh
    sees them (trimesh's own failure on such input is an unhelpful encoding error)."""
    data = path.read_bytes()
    if data.lstrip()[:5].lower() == b"solid" and b"facet" in data[:4096]:
        return  # ASCII STL (a binary header may also start with "solid": then the length test runs)
    if len(data) >= 84:
        n_tri = int.from_bytes(data[80:84], "little")
        if len(data) == 84 + 50 * n_tri:
            return
    raise err("not a valid STL file (neither ASCII 'solid ... facet' nor a binary STL of consistent length)")


def _check_obj_bytes(path: Path, err: Callable[[str], ObjectMeshError]) -> None:
    """Refuse an .obj that is not text before trimesh sees it: trimesh guesses the encoding of binary
    data and fails with an unrelated error (a missing ``charset_normalizer`` module)."""
    data = path.read_bytes()
    try:
        data.decode("utf-8")
    except UnicodeDecodeError:
        raise err("not a mesh: an .obj file is text, this one is binary data (not UTF-8)") from None
    if b"\x00" in data:
        raise err("not a mesh: an .obj file is text, this one contains NUL bytes")


def _farthest_points(p: np.ndarray, k: int) -> np.ndarray:
    """Indices of ``k`` spread-out points of p (P, 3): greedy farthest-point sampling, deterministic."""
    idx = [int(np.argmax(np.linalg.norm(p - p.mean(0), axis=1)))]
    d = np.linalg.norm(p - p[idx[0]], axis=1)
    for _ in range(k - 1):
        idx.append(int(np.argmax(d)))
        d = np.minimum(d, np.linalg.norm(p - p[idx[-1]], axis=1))
    return np.array(idx)


def _thinned_hull(points: np.ndarray) -> _Hull:
    """Hull of ``points (P, 3)``, thinned to at most ``USER_MAX_HULL_VERTICES`` vertices: MuJoCo's
    collision cost grows with hull size; 128 well-spread vertices lose < 1 mm on a 10 cm rounded
    object."""
    hv = _hull(points).vertices
    if len(hv) > USER_MAX_HULL_VERTICES:
        hv = hv[np.sort(_farthest_points(hv, USER_MAX_HULL_VERTICES))]
    return _hull(hv)


def _user_parts(mesh, hull: _Hull, centre: np.ndarray) -> list[_Hull]:
    """Collision parts of a loaded user mesh (``trimesh.Trimesh``) in the frame centred at
    ``centre``: one hull per connected piece (when there are 2..``USER_MAX_PARTS`` of them with a
    volume), else ``hull``, the whole mesh's."""
    pieces = mesh.split(only_watertight=False) if len(mesh.faces) > 0 else []
    parts = []
    if 1 < len(pieces) <= USER_MAX_PARTS:
        for piece in pieces:
            try:
                h = _thinned_hull(np.asarray(piece.vertices, dtype=np.float64) - centre)
            except QhullError:  # a flat or degenerate piece (a stray triangle): nothing to collide
                continue
            if h.volume >= 1e-9:
                parts.append(h)
    return parts if len(parts) > 1 else [_thinned_hull(hull.vertices - centre)]


def load_user_mesh(path: str | Path) -> ObjectAsset:
    """Load one ``.obj`` / ``.stl`` mesh (units: metres) as an :class:`ObjectAsset` of split ``user``.

    Collision: one convex part per separate piece of the mesh (its connected components, up to
    ``USER_MAX_PARTS``; else the hull of the whole), each the hull of that piece thinned to at most
    ``USER_MAX_HULL_VERTICES`` vertices by farthest-point sampling. A body modelled as several
    pieces (a dumbbell's bells and bar, an L-bracket's two plates, overlapping primitives) then
    collides as those pieces, as built-in objects do; a single concave piece (a scanned mug)
    still collides as its hull (no convex decomposition is run). Surface samples
    (2048, 3) and normals come from the actual mesh surface, area-weighted, with normals made
    consistent and outward where the mesh is watertight (otherwise they follow the file's winding).
    The frame is re-centred at the volume centroid (the bounding-box centre if not watertight).

    Raises ``ObjectMeshError`` (one line naming the file) for a missing, unreadable or unparseable
    file, an empty mesh, non-finite vertices, a degenerate mesh (zero area or volume, e.g. all
    points coplanar), or a largest extent outside [2 cm, 30 cm]; extents of 20-300 are reported as
    probably millimetres (never rescaled silently).
    """
    path = Path(path)

    def err(reason: str) -> ObjectMeshError:
        return ObjectMeshError(f"{path}: {reason}")

    if not path.is_file():
        raise err("file not found")
    if path.suffix.lower() not in MESH_SUFFIXES:
        raise err(f"unsupported mesh format '{path.suffix}' (expected .obj or .stl)")
    try:
        if path.suffix.lower() == ".stl":
            _check_stl_bytes(path, err)
        else:
            _check_obj_bytes(path, err)
        import trimesh  # lazy: ~1 s import that only user meshes need

        # process=False: keep the file's raw vertices so NaNs are reported, not silently dropped.
        mesh = trimesh.load(str(path), force="mesh", process=False)
    except ObjectMeshError:
        raise
    except Exception as exc:  # trimesh raises many types for bad files; all mean "cannot parse"
        raise err(f"cannot be read as a mesh ({_one_line(exc)})") from exc
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.vertices) == 0 or len(mesh.faces) == 0:
        raise err("mesh is empty (no vertices or no triangles)")
    v = np.asarray(mesh.vertices, dtype=np.float64)
    if not np.all(np.isfinite(v)):
        raise err(f"mesh has {int((~np.isfinite(v).all(1)).sum())} non-finite (NaN/inf) vertices")
    f = np.asarray(mesh.faces, dtype=np.int64)
    if f.min() < 0 or f.max() >= len(v):
        raise err("mesh faces index vertices that do not exist")
    used = v[np.unique(f)]
    ext = used.max(0) - used.min(0)
    big = float(ext.max())
    if 20.0 <= big <= 300.0:
        raise err(
            f"largest extent is {big:g}: this looks like millimetres; meshes must be in metres "
            "(scale by 0.001)"
        )
    if big < USER_MIN_EXTENT_M or big > USER_MAX_EXTENT_M:
        raise err(
            f"largest extent {big:.4g} m is outside [{USER_MIN_EXTENT_M}, {USER_MAX_EXTENT_M}] m "
            "(meshes must be in metres)"
        )
    mesh = trimesh.Trimesh(v, f, process=True)  # merge duplicate vertices (STL) so watertight works
    if float(mesh.area) < 1e-8:
        raise err("degenerate mesh: zero surface area")
    try:
        hull_pts = mesh.vertices[ConvexHull(mesh.vertices).vertices]
        hull = _hull(hull_pts)
    except QhullError as exc:
        raise err("degenerate mesh: all vertices are coplanar or collinear (zero volume)") from exc
    if hull.volume < 1e-9:
        raise err(f"degenerate mesh: convex hull volume {hull.volume:.2e} m^3 is essentially zero")
    if mesh.is_watertight:
        mesh.fix_normals()  # consistent winding, flipped outward if the volume came out negative
        centre = np.asarray(mesh.center_mass, dtype=np.float64)
    else:
        centre = mesh.bounds.mean(axis=0)
    parts = _user_parts(mesh, hull, centre)
    tri = np.asarray(mesh.vertices, dtype=np.float64)[mesh.faces] - centre
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    good = np.linalg.norm(cross, axis=1) > 0  # zero-area faces have no normal (and get no samples)
    tri, cross = tri[good], cross[good]
    tri_n = cross / np.linalg.norm(cross, axis=1, keepdims=True)
    pts, nrm, _ = _sample_triangles(tri, tri_n, N_SURFACE_SAMPLES, np.random.default_rng(_seed(path.name)))
    allv = mesh.vertices - centre
    return ObjectAsset(
        name=path.stem,
        category="user",
        split="user",
        parts=tuple(h.vertices for h in parts),
        part_faces=tuple(h.faces for h in parts),
        surface_points=pts.astype(np.float32),
        surface_normals=nrm.astype(np.float32),
        extents=allv.max(0) - allv.min(0),
    )
