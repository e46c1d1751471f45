"""Tests for sim.objects: the built-in object set (splits, sizes, convex parts, surface samples,
determinism) and user mesh loading (valid file, and every refusal names the file)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import ConvexHull

from sim.objects import (
    N_SURFACE_SAMPLES,
    SPEC_CHOICES,
    SPLITS,
    ObjectMeshError,
    builtin_objects,
    load_objects,
    load_user_mesh,
)


@pytest.fixture(scope="module")
def objs():
    return builtin_objects()


def _plane_dist(points, verts):
    """Signed distance-like value (M,) of points to the hull of verts: <= 0 inside."""
    eq = ConvexHull(verts).equations
    return (points @ eq[:, :3].T + eq[:, 3]).max(axis=1)


# ---------------------------------------------------------------------------------------- splits


def test_set_size_names_and_splits(objs):
    assert len(objs) >= 44
    names = [o.name for o in objs]
    assert len(set(names)) == len(names)
    by_split = {s: load_objects(s) for s in SPLITS}
    sets = {s: {o.name for o in v} for s, v in by_split.items()}
    assert sets["train"].isdisjoint(sets["unseen-instance"])
    assert sets["train"].isdisjoint(sets["unseen-category"])
    assert sets["unseen-instance"].isdisjoint(sets["unseen-category"])
    assert set().union(*sets.values()) == set(names)
    assert (
        len(sets["train"]) >= 28 and len(sets["unseen-instance"]) >= 5 and len(sets["unseen-category"]) >= 5
    )
    for s, v in by_split.items():
        assert all(o.split == s for o in v)

    cats = {s: {o.category for o in v} for s, v in by_split.items()}
    assert cats["unseen-category"].isdisjoint(cats["train"])
    assert len(cats["unseen-category"]) >= 5
    assert cats["unseen-instance"] <= cats["train"]

    unseen = {o.name for o in load_objects("unseen")}
    assert unseen == sets["unseen-instance"] | sets["unseen-category"]
    assert {o.name for o in load_objects("all")} == set(names)


def test_train_extra_adds_instances_of_training_categories_only(objs, tmp_path, monkeypatch):
    extra = load_objects("train-extra")
    wide = load_objects("train-wide")
    train = load_objects("train")
    assert len(extra) == 64 and all(o.split == "train-extra" for o in extra)
    names = {o.name for o in objs}
    assert names.isdisjoint(o.name for o in extra)  # new shapes, and not part of `all`
    assert {o.name for o in wide} == {o.name for o in train} | {o.name for o in extra}
    assert {o.category for o in extra} == {o.category for o in train}  # no category is added
    assert not any(np.allclose(e.extents, o.extents) for e in extra for o in objs)  # new geometry
    for o in extra:
        assert 0.06 - 1e-9 <= o.extents.max() <= 0.13 and o.extents.min() >= 0.02 - 1e-9, o.name
    (mug,) = load_objects("mug_07")
    assert mug.split == "train-extra"
    _assert_poses_and_symmetries_ship(extra, tmp_path, monkeypatch)


def _assert_poses_and_symmetries_ship(assets, tmp_path, monkeypatch):
    """The stable poses and symmetries of ``assets`` ship: an empty cache directory is never written to."""
    from sim.goals import stable_poses
    from sim.symmetry import symmetries

    monkeypatch.setenv("HYDO_CACHE", str(tmp_path))
    for o in assets:
        assert stable_poses(o).shape == (100, 5) and symmetries(o).shape[1:] == (4, 4)
    assert not any(tmp_path.iterdir())


def test_train_varied_adds_shapes_outside_every_evaluated_category(objs, tmp_path, monkeypatch):
    """``train-varied`` is ``train-wide`` plus irregular convex bodies and stepped multi-box bodies
    (``VARIED_CATEGORIES``): new categories, for training only, never part of ``all`` or an unseen
    split; sized like the built-ins; their stable poses and symmetries ship."""
    from sim.objects import VARIED_CATEGORIES

    varied = load_objects("train-varied")
    wide = load_objects("train-wide")
    new = varied[len(wide) :]
    assert [o.name for o in varied[: len(wide)]] == [o.name for o in wide]
    assert len(new) == 32 and all(o.split == "train-varied" for o in new)
    assert {o.category for o in new} == set(VARIED_CATEGORIES)
    assert set(VARIED_CATEGORIES).isdisjoint(o.category for o in objs)  # not in `all`, nor evaluated
    assert any(len(o.parts) > 1 for o in new) and any(len(o.parts) == 1 for o in new)
    for o in new:
        assert 0.06 - 1e-9 <= o.extents.max() <= 0.13 and o.extents.min() >= 0.02 - 1e-9, o.name
    (blocks,) = load_objects("blocks_03")
    assert blocks.category == "blocks"
    _assert_poses_and_symmetries_ship(new, tmp_path, monkeypatch)


def test_cube_and_single_names(objs):
    (cube,) = load_objects("cube")
    assert cube.name == "cube"
    np.testing.assert_allclose(cube.extents, [0.06, 0.06, 0.06], atol=1e-9)
    for spec in SPEC_CHOICES:
        assert len(load_objects(spec)) >= 1
    (mug,) = load_objects("mug_02")
    assert mug.name == "mug_02" and mug.category == "mug"
    with pytest.raises(ValueError, match="unknown object spec"):
        load_objects("no_such_object")


# ------------------------------------------------------------------------------------- geometry


def test_sizes_and_parts(objs):
    for o in objs:
        assert 0.06 - 1e-9 <= o.extents.max() <= 0.13, o.name
        assert o.extents.min() >= 0.02 - 1e-9, o.name
        assert 1 <= len(o.parts) <= 16 and len(o.parts) == len(o.part_faces), o.name
        allv = np.concatenate(o.parts)
        np.testing.assert_allclose(allv.max(0) - allv.min(0), o.extents, atol=1e-12)
        for v, f in zip(o.parts, o.part_faces, strict=True):
            assert v.ndim == 2 and v.shape[1] == 3 and len(v) <= 64, o.name
            assert np.all(np.isfinite(v)), o.name
            hull = ConvexHull(v)
            assert hull.volume > 1e-7, o.name
            # Convex: every stored vertex is a hull vertex, and the stored (outward-wound) faces
            # enclose exactly the hull's volume (divergence theorem; negative if wound inward).
            assert len(hull.vertices) == len(v), o.name
            a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
            vol = np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0
            assert vol == pytest.approx(hull.volume, rel=1e-6), o.name


def test_centred_at_volume_centroid(objs):
    # Parts do not overlap (mug handles only marginally), so the volume-weighted centroid is ~0.
    for o in objs:
        hulls = [ConvexHull(v) for v in o.parts]
        vol = np.array([h.volume for h in hulls])
        cents = []
        for v, h in zip(o.parts, hulls, strict=True):
            m = v.mean(0)
            t = v[h.simplices]
            w = np.abs(np.einsum("ij,ij->i", t[:, 0] - m, np.cross(t[:, 1] - m, t[:, 2] - m)))
            cents.append((w[:, None] * (t.sum(1) + m)).sum(0) / (4 * w.sum()))
        c = (vol[:, None] * np.array(cents)).sum(0) / vol.sum()
        assert np.linalg.norm(c) < 1e-3, o.name


def test_surface_samples_outward(objs):
    for o in objs:
        p, n = o.surface_points, o.surface_normals
        assert p.shape == (N_SURFACE_SAMPLES, 3) and n.shape == (N_SURFACE_SAMPLES, 3)
        assert p.dtype == np.float32 and n.dtype == np.float32
        np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-5)
        p64, n64 = p.astype(np.float64), n.astype(np.float64)
        out = np.stack([_plane_dist(p64 + 0.003 * n64, v) for v in o.parts]).min(0)
        inn = np.stack([_plane_dist(p64 - 0.001 * n64, v) for v in o.parts]).min(0)
        assert np.mean(out > 0) >= 0.95, o.name  # 3 mm outwards leaves the object
        assert np.mean(inn <= 1e-6) >= 0.95, o.name  # 1 mm inwards is inside some part
        # Samples lie on the surface: on (not strictly inside) the closest part's boundary.
        on = np.stack([_plane_dist(p64, v) for v in o.parts]).min(0)
        assert np.all(np.abs(on) < 1e-5), o.name


def test_deterministic():
    first = builtin_objects()
    builtin_objects.cache_clear()
    second = builtin_objects()
    assert first is not second
    for a, b in zip(first, second, strict=True):
        assert a.name == b.name and a.split == b.split and a.category == b.category
        for x, y in zip(a.parts + a.part_faces, b.parts + b.part_faces, strict=True):
            np.testing.assert_array_equal(x, y)
        np.testing.assert_array_equal(a.surface_points, b.surface_points)
        np.testing.assert_array_equal(a.surface_normals, b.surface_normals)
        np.testing.assert_array_equal(a.extents, b.extents)


def test_cached_arrays_are_read_only(objs):
    with pytest.raises(ValueError):
        objs[0].surface_points[0, 0] = 1.0


# ---------------------------------------------------------------------------------- user meshes


def _export_box(path, extents):
    import trimesh

    trimesh.creation.box(extents=extents).export(str(path))


def test_user_mesh_valid(tmp_path):
    f = tmp_path / "block.stl"
    _export_box(f, [0.08, 0.05, 0.03])
    (o,) = load_objects(str(f))
    assert o.name == "block" and o.split == "user" and len(o.parts) == 1
    np.testing.assert_allclose(o.extents, [0.08, 0.05, 0.03], atol=1e-9)
    assert o.surface_points.shape == (N_SURFACE_SAMPLES, 3)
    np.testing.assert_allclose(np.linalg.norm(o.surface_normals, axis=1), 1.0, atol=1e-5)
    out = _plane_dist(o.surface_points + 0.003 * o.surface_normals, o.parts[0])
    assert np.all(out > 0)  # outward normals
    np.testing.assert_allclose(o.surface_points.mean(0), 0.0, atol=2e-3)  # centred
    # A folder loads every .obj/.stl in it.
    _export_box(tmp_path / "other.obj", [0.05, 0.05, 0.05])
    (tmp_path / "notes.txt").write_text("not a mesh")
    assert [o.name for o in load_objects(tmp_path)] == ["block", "other"]


@pytest.mark.parametrize(
    "fname, content, match",
    [
        ("garbage.stl", b"\x00\x01\x02 this is not a mesh " * 3, "not a valid STL"),
        ("garbage.obj", b"hello world\n", "empty"),
        (
            "nan.obj",
            b"v nan 0 0\nv 0.05 0 0\nv 0 0.05 0\nv 0 0 0.05\nf 1 2 3\nf 1 2 4\nf 1 3 4\nf 2 3 4\n",
            "non-finite",
        ),
        ("flat.obj", b"v 0 0 0\nv 0.05 0 0\nv 0 0.05 0\nv 0.05 0.05 0\nf 1 2 3\nf 2 4 3\n", "degenerate"),
    ],
)
def test_user_mesh_refused(tmp_path, fname, content, match):
    f = tmp_path / fname
    f.write_bytes(content)
    with pytest.raises(ObjectMeshError, match=match) as e:
        load_user_mesh(f)
    assert fname in str(e.value) and "\n" not in str(e.value)


def test_user_mesh_bad_size(tmp_path):
    f = tmp_path / "metre_cube.stl"
    _export_box(f, [1.0, 1.0, 1.0])
    with pytest.raises(ObjectMeshError, match="outside") as e:
        load_user_mesh(f)
    assert "metre_cube.stl" in str(e.value)

    f = tmp_path / "mm_cube.obj"
    _export_box(f, [50.0, 50.0, 50.0])
    with pytest.raises(ObjectMeshError, match="millimetres") as e:
        load_objects(str(f))
    assert "mm_cube.obj" in str(e.value)


def test_missing_and_empty_folder(tmp_path):
    with pytest.raises(ObjectMeshError, match="no .obj or .stl") as e:
        load_objects(str(tmp_path))
    assert str(tmp_path) in str(e.value)
    with pytest.raises(ObjectMeshError, match="not found"):
        load_objects(str(tmp_path / "missing.obj"))


def test_user_mesh_of_separate_pieces_collides_as_the_pieces(tmp_path):
    """An L-bracket modelled as two boxes (two connected pieces in one file) gets one convex part
    per box: the inner corner of the L, inside the hull of the whole, is inside neither part, so
    the simulator leaves it empty as a real bracket does. A one-piece mesh keeps one hull."""
    import trimesh

    plate = trimesh.creation.box((0.09, 0.03, 0.02))
    upright = trimesh.creation.box((0.02, 0.03, 0.06)).apply_translation((0.035, 0.0, 0.04))
    f = tmp_path / "l_bracket.obj"
    trimesh.util.concatenate([plate, upright]).export(str(f))
    (o,) = load_objects(str(f))
    assert len(o.parts) == 2
    assert sorted(len(p) for p in o.parts) == [8, 8]  # two boxes' corners
    lo = np.min([p.min(0) for p in o.parts], axis=0)  # the frame is re-centred: place it from the parts
    corner = lo + np.array([0.03, 0.015, 0.03])  # 1 cm above the plate, 4 cm left of the upright
    assert all(_plane_dist(corner[None], p)[0] > 0.005 for p in o.parts)  # outside both boxes
    assert _plane_dist(corner[None], np.concatenate(o.parts))[0] < 0  # inside the hull of the whole
    # every surface sample lies on one of the parts (within a hair)
    assert np.min([_plane_dist(o.surface_points, p) for p in o.parts], axis=0).max() < 1e-6
