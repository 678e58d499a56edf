"""Index fingertip geometry and mesh (handfe.fingertip), reduced level.

Reference volumes: the bi-ellipsoid body and the bone are closed-form
(FingertipGeometry.outer_volume_mm3 / bone_volume_mm3); the nail region is integrated on a
fine grid from its defining inequalities (independent of gmsh/OCC)."""

import numpy as np
import pytest
from mpi4py import MPI

from handfe.errors import InputError
from handfe.fingertip import (
    CELL_TAGS,
    FACET_TAGS,
    build_fingertip_mesh,
    fingertip_geometry,
    mesh_sizes,
)


@pytest.fixture(scope="module")
def geom():
    return fingertip_geometry()


@pytest.fixture(scope="module")
def fm(geom):
    return build_fingertip_mesh(geom, level="reduced", comm=MPI.COMM_WORLD)


@pytest.fixture(scope="module")
def fm_layered(geom):
    return build_fingertip_mesh(geom, level="reduced", layered=True, skin_thickness_mm=1.0,
                                comm=MPI.COMM_WORLD)


def _cell_volumes(fmesh, name):
    msh = fmesh.mesh
    n_owned = msh.topology.index_map(3).size_local
    cells = fmesh.cell_tags.find(fmesh.tags[name])
    cells = cells[cells < n_owned]
    geo = msh.geometry.dofmap.array.reshape(-1, 4)
    x = msh.geometry.x[geo[cells]]
    v = np.abs(np.einsum("ij,ij->i", np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]),
                         x[:, 3] - x[:, 0])) / 6.0
    return msh.comm.allreduce(float(v.sum()), op=MPI.SUM)


def _facets(fmesh, name):
    """Deformation-free triangles (n, 3, 3) of a facet tag, gathered from all ranks."""
    from dolfinx import cpp

    msh = fmesh.mesh
    msh.topology.create_entities(2)
    n_owned = msh.topology.index_map(2).size_local
    f = fmesh.facet_tags.find(fmesh.tags[name])
    f = f[f < n_owned]
    nodes = cpp.mesh.entities_to_geometry(msh._mesh, 2, f, False)
    tri = msh.geometry.x[nodes]
    return np.concatenate(msh.comm.allgather(tri), axis=0)


def _ray_z(tri, x, y):
    """z of the triangles hit by the vertical line through (x, y)."""
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    det = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (c[:, 0] - a[:, 0]) * (b[:, 1] - a[:, 1])
    ok = np.abs(det) > 1e-14
    l1 = ((x - a[:, 0]) * (c[:, 1] - a[:, 1]) - (c[:, 0] - a[:, 0]) * (y - a[:, 1])) / np.where(
        ok, det, 1)
    l2 = ((b[:, 0] - a[:, 0]) * (y - a[:, 1]) - (x - a[:, 0]) * (b[:, 1] - a[:, 1])) / np.where(
        ok, det, 1)
    hit = ok & (l1 >= -1e-12) & (l2 >= -1e-12) & (l1 + l2 <= 1 + 1e-12)
    return a[hit, 2] + l1[hit] * (b[hit, 2] - a[hit, 2]) + l2[hit] * (c[hit, 2] - a[hit, 2])


def _nail_volume_grid(g, h=0.04):
    """Nail region: inside the body, outside the body shrunk by the nail thickness,
    z >= nail_z_min, x >= nail_start: midpoint rule on a grid."""
    xs = np.arange(g.nail_start_x_mm + h / 2, g.length_mm, h)
    ys = np.arange(-g.half_width_mm + h / 2, g.half_width_mm, h)
    zs = np.arange(g.nail_z_min_mm + h / 2, g.dorsal_height_mm, h)
    X, Y, Z = np.meshgrid(xs, ys, zs, indexing="ij")

    def inside(t):
        u = np.maximum(X - g.proximal_length_mm, 0) / (g.tip_length_mm - t)
        return u**2 + (Y / (g.half_width_mm - t)) ** 2 + (Z / (g.dorsal_height_mm - t)) ** 2 <= 1

    return float(np.count_nonzero(inside(0.0) & ~inside(g.nail_thickness_mm))) * h**3


def test_geometry_mean_row(geom):
    g = geom
    assert (g.w0_mm, g.h0_mm, g.wp_mm, g.hp_mm, g.DN0_mm) == (16.7, 12.0, 7.4, 4.0, 6.4)
    assert g.half_width_mm == pytest.approx(8.35)
    assert g.palmar_depth_mm + g.dorsal_height_mm == pytest.approx(12.0)
    # pulp thickness under the bone (flat part) = DN0, along the axis from the tip = DN90
    assert g.bone_bottom_mm - (-g.palmar_depth_mm) == pytest.approx(6.4)
    assert g.DN90_model_mm == pytest.approx(2.3, abs=1e-6)
    assert g.bone_tip_x_mm < g.length_mm
    s1 = fingertip_geometry("S1")
    assert (s1.w0_mm, s1.DN0_mm) == (16.0, 7.5)
    for s in ("S2", "S3", "S4", "S5"):
        gs = fingertip_geometry(s)
        assert gs.bone_bottom_mm + gs.palmar_depth_mm == pytest.approx(gs.DN0_mm)


def test_levels_ordered_coarse_for_tests():
    """'coarse' (for fast tests of other modules, not validated) is the coarsest level, each
    level is no coarser than the one before and has a finer pad, and each level's pad is
    finer than its global size; an explicit pad size overrides."""
    names = ("coarse", "reduced", "default", "fine")
    sizes = [mesh_sizes(n) for n in names]
    assert sizes[0] == (3.5, 2.0)
    assert all(a[0] >= b[0] and a[1] > b[1] for a, b in zip(sizes[:-1], sizes[1:], strict=True))
    assert all(h_pad < h for h, h_pad in sizes)
    assert mesh_sizes(h_mm=2.0) == (2.0, pytest.approx(1.2))
    assert mesh_sizes(h_mm=2.0, h_pad_mm=0.8) == (2.0, 0.8)
    assert mesh_sizes("reduced", h_pad_mm=1.0) == (2.5, 1.0)


def test_bad_input(geom):
    with pytest.raises(InputError, match="S9"):
        fingertip_geometry("S9")
    with pytest.raises(InputError, match="mesh level"):
        mesh_sizes("tiny")
    with pytest.raises(InputError, match="h_mm"):
        mesh_sizes(h_mm=-1.0)
    with pytest.raises(InputError, match="h_pad_mm.*3"):
        mesh_sizes(h_mm=2.0, h_pad_mm=3.0)
    with pytest.raises(InputError, match="skin_thickness"):
        build_fingertip_mesh(geom, level="reduced", layered=True, skin_thickness_mm=10.0)


@pytest.mark.parametrize("argv,needle", [
    (["--h-pad", "3"], "--h-pad must be within 0.2 mm..the global size 2.5 mm, got 3.0"),
    (["--h", "9"], "--h must be within 0.2..5 mm, got 9.0"),
])
def test_cli_size_errors_name_the_flag(argv, needle, capsys):
    """Bad sizes are refused before any meshing, naming the command-line flag."""
    from handfe.cli import main

    assert main(["fingertip", "--force", "1", "--out", "unused", *argv]) == 2
    assert needle in capsys.readouterr().err


@pytest.mark.mpi
def test_tags_present(fm):
    comm = fm.mesh.comm
    assert set(fm.tags) == {"pulp", "nail"} | set(FACET_TAGS)
    assert fm.tags["pulp"] == CELL_TAGS["pulp"]
    assert all(fm.cells_per_tag[k] > 0 for k in ("pulp", "nail"))
    assert fm.cells_per_tag["pulp"] + fm.cells_per_tag["nail"] == fm.num_cells
    for name in FACET_TAGS:
        n = comm.allreduce(len(fm.facet_tags.find(fm.tags[name])), op=MPI.SUM)
        assert n > 0, name
    np.testing.assert_allclose(fm.finger_axis, [1, 0, 0])
    np.testing.assert_allclose(fm.pad_normal, [0, 0, -1])
    assert fm.meshing_time_s > 0


@pytest.mark.mpi
def test_volumes_and_surfaces(fm, geom):
    g = geom
    v_pulp = _cell_volumes(fm, "pulp")
    v_nail = _cell_volumes(fm, "nail")
    body, bone = g.outer_volume_mm3(), g.bone_volume_mm3()
    assert v_pulp + v_nail == pytest.approx(body - bone, rel=0.03)
    assert v_nail == pytest.approx(_nail_volume_grid(g), rel=0.10)
    pad = _facets(fm, "pad")
    assert pad[..., 2].max() <= 1e-9  # the pad is the palmar half
    prox = _facets(fm, "proximal")
    assert np.abs(prox[..., 0]).max() < 1e-9
    bone_t = _facets(fm, "bone")
    assert bone_t[..., 0].max() == pytest.approx(g.bone_tip_x_mm, abs=0.05)
    # pulp thickness under the bone on vertical lines through the flat part = DN0, within
    # the chord error (sagitta h^2 / 8R) of the bone and pad sections at their lowest point
    r_bone = (g.wp_mm / 2) ** 2 / (g.hp_mm / 2)
    r_pad = g.half_width_mm**2 / g.palmar_depth_mm
    tol = fm.h_mm**2 / (8 * r_bone) + fm.h_pad_mm**2 / (8 * r_pad)
    for x in (3.0, 6.0, 9.0):
        z_pad = _ray_z(pad, x, 0.0)
        z_bone = _ray_z(bone_t, x, 0.0)
        assert len(z_pad) and len(z_bone)
        assert z_bone.min() - z_pad.min() == pytest.approx(g.DN0_mm, abs=tol)


def test_layered_volumes(fm_layered, geom):
    g = geom
    assert {"skin", "subcutaneous", "nail"} <= set(fm_layered.tags)
    assert "pulp" not in fm_layered.tags
    v_skin = _cell_volumes(fm_layered, "skin")
    v_sub = _cell_volumes(fm_layered, "subcutaneous")
    v_nail = _cell_volumes(fm_layered, "nail")
    shell = g.outer_volume_mm3() - g.outer_volume_mm3(1.0)  # nail lies inside the 1 mm shell
    assert v_skin + v_nail == pytest.approx(shell, rel=0.05)
    assert v_sub == pytest.approx(g.outer_volume_mm3(1.0) - g.bone_volume_mm3(), rel=0.03)


def _surface_area(fmesh, name):
    t = _facets(fmesh, name)  # gathered from all ranks
    return float(0.5 * np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]),
                                      axis=1).sum())


@pytest.mark.mpi
def test_half_model_is_half_of_the_fingertip(fm, geom):
    """half=True: y >= 0 only, the cut face y = 0 tagged ``symmetry``, volumes and surfaces
    half of the whole fingertip's (within the chord error of two different meshes)."""
    from handfe.fingertip import SYMMETRY_TAG

    half = build_fingertip_mesh(geom, level="reduced", half=True, comm=MPI.COMM_WORLD)
    assert half.half and half.tags["symmetry"] == SYMMETRY_TAG
    comm = half.mesh.comm
    y = half.mesh.geometry.x[:, 1]
    assert comm.allreduce(float(y.min(initial=0.0)), op=MPI.MIN) >= -1e-9
    sym = _facets(half, "symmetry")
    assert np.abs(sym[..., 1]).max() < 1e-9
    # the cut face is the sagittal section of the tissue (body minus bone, at x >= 0)
    assert _surface_area(half, "symmetry") > 100.0
    for name in ("pulp", "nail"):
        assert _cell_volumes(half, name) == pytest.approx(0.5 * _cell_volumes(fm, name),
                                                          rel=0.02), name
    for name in FACET_TAGS:
        assert _surface_area(half, name) == pytest.approx(0.5 * _surface_area(fm, name),
                                                          rel=0.02), name


def test_mesh_cache_gives_the_same_mesh(geom, tmp_path, monkeypatch):
    """A mesh made once is read back from the cache (HANDFE_CACHE_DIR) identically: same
    vertices, cells and tags; an unreadable file is meshed afresh; other inputs miss;
    HANDFE_MESH_CACHE=0 bypasses it."""
    monkeypatch.setenv("HANDFE_CACHE_DIR", str(tmp_path))
    monkeypatch.delenv("HANDFE_MESH_CACHE", raising=False)
    a = build_fingertip_mesh(geom, level="coarse", half=True, comm=MPI.COMM_SELF)
    b = build_fingertip_mesh(geom, level="coarse", half=True, comm=MPI.COMM_SELF)
    assert not a.from_cache and b.from_cache
    assert len(list((tmp_path / "meshes").glob("*.msh"))) == 1
    np.testing.assert_array_equal(a.mesh.geometry.x, b.mesh.geometry.x)
    np.testing.assert_array_equal(a.mesh.geometry.dofmap.array, b.mesh.geometry.dofmap.array)
    for t in ("cell_tags", "facet_tags"):
        np.testing.assert_array_equal(getattr(a, t).indices, getattr(b, t).indices)
        np.testing.assert_array_equal(getattr(a, t).values, getattr(b, t).values)
    # an unreadable cache file is replaced by a fresh mesh
    (f,) = (tmp_path / "meshes").glob("*.msh")
    f.write_bytes(b"not a mesh")
    c = build_fingertip_mesh(geom, level="coarse", half=True, comm=MPI.COMM_SELF)
    assert not c.from_cache and c.num_cells == a.num_cells and f.stat().st_size > 1000
    assert not build_fingertip_mesh(geom, level="coarse", comm=MPI.COMM_SELF).from_cache
    monkeypatch.setenv("HANDFE_MESH_CACHE", "0")
    assert not build_fingertip_mesh(geom, level="coarse", half=True,
                                    comm=MPI.COMM_SELF).from_cache


@pytest.mark.mpi
def test_mpi_same_mesh_as_serial(fm):
    """The distributed mesh is the serial one: same global counts and tagged volumes."""
    if fm.mesh.comm.size == 1:
        pytest.skip("compares COMM_WORLD with COMM_SELF: meaningful under mpirun")
    serial = build_fingertip_mesh(fm.geometry, level="reduced", comm=MPI.COMM_SELF)
    assert serial.num_cells == fm.num_cells
    assert serial.cells_per_tag == fm.cells_per_tag
    for name in ("pulp", "nail"):
        assert _cell_volumes(fm, name) == pytest.approx(_cell_volumes(serial, name), rel=1e-12)


@pytest.mark.mpi
def test_plate_first_contact_on_pad(fm, geom):
    """contact_metrics on the fingertip with a P2 displacement (zero): the gap of a 15 deg
    plate to the pad equals the first-contact distance of the exact bi-ellipsoid (densely
    sampled) within the chord error; pushing it 1 mm further gives a patch on the pad."""
    from dolfinx import fem

    from handfe.contact import contact_metrics, plate

    g = geom
    ob = plate(15.0, point=(0.0, 0.0, -20.0))
    n = np.asarray(ob.normal)
    # exact: min over the palmar surface of (x - p0) . n
    th, ph = np.meshgrid(np.linspace(0, np.pi / 2, 801), np.linspace(0, np.pi, 801))
    cap = np.stack([g.proximal_length_mm + g.tip_length_mm * np.sin(th) * np.ones_like(ph),
                    g.half_width_mm * np.cos(th) * np.cos(ph),
                    -g.palmar_depth_mm * np.cos(th) * np.sin(ph)], axis=-1).reshape(-1, 3)
    exact = float(np.min(ob.gap_normal(cap)[0]))
    u = fem.Function(fem.VectorFunctionSpace(fm.mesh, ("CG", 2)))
    comm = fm.mesh.comm
    m0 = contact_metrics(u, ob, (0, 0, 0), fm.facet_tags, fm.tags["pad"], comm=comm)
    assert m0.min_gap_mm == pytest.approx(exact, abs=0.1)
    assert m0.contact_area_mm2 == 0.0
    m1 = contact_metrics(u, ob, tuple((m0.min_gap_mm + 1.0) * n), fm.facet_tags,
                         fm.tags["pad"], comm=comm,
                         axes=((np.cos(np.radians(15)), 0, np.sin(np.radians(15))), (0, 1, 0)))
    assert m1.max_penetration_mm == pytest.approx(1.0, abs=1e-9)
    assert 10.0 < m1.contact_area_mm2 < 200.0
    assert m1.length_mm > 0 and m1.width_mm > 0
    assert abs(m1.centroid_mm[1]) < 0.2 * m1.width_mm  # symmetric across the finger


def test_thin_subject_s3_meshes():
    """S3 has only 0.6 mm over the bone: the nail is thinned to fit and the mesh is built."""
    g = fingertip_geometry("S3")
    assert g.nail_thickness_mm == pytest.approx(0.3)
    m = build_fingertip_mesh(g, level="reduced", comm=MPI.COMM_SELF)
    assert m.cells_per_tag["nail"] > 0 and m.cells_per_tag["pulp"] > 0
    assert _cell_volumes(m, "pulp") + _cell_volumes(m, "nail") == pytest.approx(
        g.outer_volume_mm3() - g.bone_volume_mm3(), rel=0.03)


def test_gmsh_usable_for_the_hand_after_a_fingertip_mesh(fm):
    """The fingertip scene finalises gmsh; the hand meshing's once-per-process initialisation
    must notice (it did not: the CI's pinch test then failed on rank 0 with gmsh's "Could not
    get last error" and left rank 1 waiting)."""
    import gmsh

    from handfe.anatomy.meshing import ensure_gmsh

    if MPI.COMM_WORLD.rank == 0:
        build_fingertip_mesh(fm.geometry, level="reduced", comm=MPI.COMM_SELF)
        ensure_gmsh(gmsh)
        gmsh.option.setNumber("General.Terminal", 0)  # raises on a finalised gmsh
        gmsh.model.add("after_fingertip")
        gmsh.model.remove()
