import logging

import numpy as np
import pytest
from shapes import bumpy, sphere

import geofeat
from geofeat import Mesh
from geofeat.errors import MeshError


def write_off(path, verts, faces):
    lines = ["OFF", f"{len(verts)} {len(faces)} 0"]
    lines += [" ".join(f"{x:.17g}" for x in v) for v in verts]
    lines += ["3 " + " ".join(str(i) for i in f) for f in faces]
    path.write_text("\n".join(lines) + "\n")


def write_obj(path, verts, faces):
    lines = ["# test", "o shape"] + [f"v {x:.17g} {y:.17g} {z:.17g}" for x, y, z in verts]
    lines += ["vt 0 0", "vn 0 0 1"]
    lines += ["f " + " ".join(f"{i + 1}/1/1" for i in f) for f in faces]
    path.write_text("\n".join(lines) + "\n")


def write_ply(path, verts, faces, binary=True):
    import trimesh

    data = trimesh.exchange.ply.export_ply(trimesh.Trimesh(verts, faces, process=False), encoding="binary" if binary else "ascii")
    path.write_bytes(data)


@pytest.fixture
def shuffled():
    """A mesh whose vertex order is random and which holds a duplicated vertex (must survive loading)."""
    mesh = bumpy(1, 2)
    rng = np.random.default_rng(0)
    perm = rng.permutation(mesh.n_vertices)
    inverse = np.argsort(perm)
    verts = np.vstack([mesh.verts[perm], mesh.verts[perm][:1]])  # last vertex duplicates the first
    faces = inverse[mesh.faces]
    return verts, faces


@pytest.mark.parametrize("suffix,writer", [(".off", write_off), (".obj", write_obj), (".ply", write_ply)])
def test_load_keeps_vertex_order_and_duplicates(tmp_path, shuffled, suffix, writer):
    verts, faces = shuffled
    path = tmp_path / f"shape{suffix}"
    writer(path, verts, faces)
    mesh = geofeat.load_mesh(path)
    assert mesh.name == "shape"
    assert mesh.verts.dtype == np.float64 and mesh.faces.dtype == np.int64
    np.testing.assert_allclose(mesh.verts, verts, rtol=0, atol=1e-6 if suffix == ".ply" else 0)
    np.testing.assert_array_equal(mesh.faces, faces)


def test_ascii_ply_and_point_cloud_ply(tmp_path, shuffled):
    verts, faces = shuffled
    write_ply(tmp_path / "a.ply", verts, faces, binary=False)
    np.testing.assert_array_equal(geofeat.load_mesh(tmp_path / "a.ply").faces, faces)
    import trimesh

    (tmp_path / "p.ply").write_bytes(trimesh.exchange.ply.export_ply(trimesh.PointCloud(verts)))
    cloud = geofeat.load_mesh(tmp_path / "p.ply")
    assert cloud.is_point_cloud and cloud.n_vertices == len(verts)


def test_faust_shape_loads_with_its_vertex_count(faust_mesh):
    assert faust_mesh.verts.shape == (4999, 3)
    assert faust_mesh.faces.shape[1] == 3
    assert faust_mesh.report() == []


def test_off_header_on_one_line_and_comments(tmp_path):
    (tmp_path / "t.off").write_text("OFF 3 1 0\n# comment\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n")
    mesh = geofeat.load_mesh(tmp_path / "t.off")
    assert mesh.faces.tolist() == [[0, 1, 2]]


@pytest.mark.parametrize(
    "text,match",
    [
        ("OFF\n4 1 0\n0 0 0\n1 0 0\n1 1 0\n0 1 0\n4 0 1 2 3\n", "only triangles"),
        ("OFF\n3 1 0\n0 0 0\n1 0 0\n", "file ends"),
        ("COFF\n3 1 0\n0 0 0 1 1 1 1\n1 0 0 1 1 1 1\n0 1 0 1 1 1 1\n3 0 1 2\n", "'COFF' is not supported"),
        ("PLY\n", "not an OFF file"),
        ("OFF\n3 1 0\n0 0 nan\n1 0 0\n0 1 0\n3 0 1 2\n", "NaN or infinite"),
        ("OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 1 2 3\n", r"range \[1, 3\]"),
    ],
)
def test_bad_off_files_raise_clear_errors(tmp_path, text, match):
    path = tmp_path / "bad.off"
    path.write_text(text)
    with pytest.raises(MeshError, match=match) as info:
        geofeat.load_mesh(path)
    assert "bad.off" in str(info.value)
    assert isinstance(info.value, geofeat.GeofeatError)


def test_quad_in_ply_and_obj_is_refused(tmp_path):
    ply = (
        "ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\n"
        "element face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n1 1 0\n0 1 0\n4 0 1 2 3\n"
    )
    (tmp_path / "q.ply").write_text(ply)
    with pytest.raises(MeshError, match="only triangles"):
        geofeat.load_mesh(tmp_path / "q.ply")
    (tmp_path / "q.obj").write_text("v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nf 1 2 3 4\n")
    with pytest.raises(MeshError, match="only triangles"):
        geofeat.load_mesh(tmp_path / "q.obj")


def test_missing_file_and_unknown_suffix(tmp_path):
    with pytest.raises(MeshError, match="no such file"):
        geofeat.load_mesh(tmp_path / "nope.off")
    (tmp_path / "x.stl").write_text("solid")
    with pytest.raises(MeshError, match="unsupported suffix"):
        geofeat.load_mesh(tmp_path / "x.stl")


@pytest.mark.parametrize(
    "verts,faces,match",
    [
        (np.zeros((0, 3)), None, "empty"),
        (np.zeros((4, 2)), None, r"shape \(V, 3\)"),
        (np.array([["a", "b", "c"]]), None, "real numeric"),
        (np.zeros((3, 3), dtype=complex), None, "real numeric"),
        (np.array([[0, 0, 0], [1, 0, np.inf], [0, 1, 0.0]]), None, "NaN or infinite"),
        (np.eye(3), np.array([[0, 1, 3]]), r"range \[0, 3\]"),
        (np.eye(3), np.array([[-1, 1, 2]]), r"range \[-1, 2\]"),
        (np.eye(3), np.array([[0.0, 1.0, 2.0]]), "integer"),
        (np.eye(3), np.array([[0, 1, 2, 0]]), "4-sided"),
        (np.eye(3), np.array([0, 1, 2]), r"shape \(F, 3\)"),
        (np.eye(3), np.zeros((0, 3), dtype=int), "at least one face"),
    ],
)
def test_array_validation(verts, faces, match):
    with pytest.raises(MeshError, match=match):
        Mesh(verts, faces)


def test_problems_are_reported_and_handled(caplog):
    base = sphere(1)
    # 2 components, 1 unreferenced vertex, and one more vertex (for a face of zero area)
    verts = np.vstack([base.verts, base.verts + 5.0, [[9.0, 9.0, 9.0]], base.verts[:1]])
    n = base.n_vertices
    # a face naming a vertex twice (dropped), a zero-area face, more faces on edge (a, b), and a repeat of face 0
    a, b, c = base.faces[0]  # an edge (a, b) of the sphere; the extra vertex is put at a
    verts[2 * n + 1] = verts[a]
    extra_faces = np.array([[a, b, b], [b, a, 2 * n + 1], [a, b, n - 1], [c, b, a]])
    faces = np.vstack([base.faces, base.faces + n, extra_faces])
    with caplog.at_level(logging.WARNING, logger="geofeat"):
        mesh = Mesh(verts, faces, name="messy")
    text = caplog.text
    for expected in [
        "dropped 1 face(s) that name one vertex twice",
        "dropped 1 repeated face(s)",
        "1 degenerate face",
        "unreferenced vertex",
        "non-manifold edge",
        "connected components",
    ]:
        assert expected in text
    assert len(mesh.faces) == len(faces) - 2
    feats = geofeat.compute(mesh, "wks", cache=False, n_eig=20, n_descr=8)
    assert feats.shape == (len(verts), 8) and np.isfinite(feats).all()


def test_quiet_reports_silences_the_report_of_meshes_made_in_the_block(caplog):
    from geofeat.mesh import quiet_reports

    base = sphere(1)
    two = Mesh(np.vstack([base.verts, base.verts + 5.0]), np.vstack([base.faces, base.faces + base.n_vertices]))
    with caplog.at_level(logging.WARNING, logger="geofeat"):
        with quiet_reports():
            quiet = Mesh(two.verts, two.faces, name="quiet")
        Mesh(two.verts, two.faces, name="loud")
    assert "'quiet'" not in caplog.text and "mesh 'loud': 2 connected components" in caplog.text
    assert any("components" in problem for problem in quiet.report())  # still listed on request


def test_hash_depends_on_arrays_only_and_arrays_are_frozen():
    a = sphere(1)
    b = Mesh(a.verts.copy(), a.faces.copy(), name="other name")
    assert a.hash == b.hash
    moved = a.verts.copy()
    moved[0, 0] += 1e-12
    assert Mesh(moved, a.faces).hash != a.hash
    assert Mesh(a.verts).hash != a.hash  # point cloud of the same vertices
    with pytest.raises(ValueError):
        a.verts[0, 0] = 1.0


def test_normalize_gives_unit_area_and_keeps_order():
    mesh = Mesh(sphere(2).verts * 3.0 + 7.0, sphere(2).faces)
    unit = geofeat.normalize(mesh)
    assert abs(unit.area() - 1.0) < 1e-12
    assert np.allclose(unit.verts.mean(axis=0), 0, atol=1e-3)
    np.testing.assert_array_equal(unit.faces, mesh.faces)
    with pytest.raises(MeshError, match="point cloud"):
        geofeat.normalize(Mesh(mesh.verts))


def test_face_areas_and_centroid_are_computed_once_read_only_and_true():
    mesh = bumpy(0, 2)
    areas, centroid = mesh.face_areas(), mesh.centroid()
    assert mesh.face_areas() is areas and mesh.centroid() is centroid  # kept on the mesh
    assert not areas.flags.writeable and not centroid.flags.writeable
    tri = mesh.verts[mesh.faces]
    expected = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    np.testing.assert_allclose(areas, expected, rtol=1e-12)
    np.testing.assert_allclose(centroid, (tri.mean(axis=1) * expected[:, None]).sum(axis=0) / expected.sum(), rtol=1e-12)
    renamed = mesh.renamed("other")
    np.testing.assert_array_equal(renamed.face_areas(), areas)
    flat = geofeat.Mesh(np.zeros((3, 3)), np.array([[0, 1, 2]]), name="flat")
    with pytest.raises(MeshError, match="zero surface area"):
        flat.centroid()
    with pytest.raises(MeshError, match="point cloud"):
        geofeat.Mesh(np.zeros((3, 3))).centroid()


def test_normalize_about_the_mean_vertex_in_the_frame_of_another_mesh():
    full = Mesh(sphere(2).verts * 3.0 + 7.0, sphere(2).faces)
    part = Mesh(full.verts[:20] + 0.5, None)  # any vertices: normalised in the full shape's frame
    moved = geofeat.normalize(part, center="mean", frame=full)
    np.testing.assert_allclose(moved.verts, (part.verts - full.verts.mean(axis=0)) / np.sqrt(full.area()), rtol=1e-12)
    unit = geofeat.normalize(full, center="mean")
    np.testing.assert_allclose(unit.verts.mean(axis=0), 0, atol=1e-12)
    np.testing.assert_allclose(geofeat.normalize(full, center=False).verts, full.verts / np.sqrt(full.area()), rtol=1e-12)
    with pytest.raises(MeshError, match="center must be"):
        geofeat.normalize(full, center="median")
