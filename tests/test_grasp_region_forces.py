"""Per-region contact forces of the grasp outputs from consistent nodal forces
(handfe.grasp.outputs): every node's force is shared by the outer-skin facets around it, so the
regions partition the total exactly, also across MPI ranks (run under ``make test-mpi`` too).

Unit cube, 4x4x4 tets; its top face z = 1 is "outer skin", split into an index-pad region
(x < 1/2) and a middle-pad region; a rigid plate above it (obstacle normal -z). Each top node
pushes the plate with (tx, 0, 1) N."""

from types import SimpleNamespace

import numpy as np
import pytest
from mpi4py import MPI

from handfe.anatomy.meshing import SKIN_OUTER_GMSH
from handfe.contact import HalfSpace
from handfe.grasp.outputs import facet_data, loaded_area, region_metrics

N = 4
INDEX_DISTAL = SKIN_OUTER_GMSH + 10 * 2 + 3
MIDDLE_DISTAL = SKIN_OUTER_GMSH + 10 * 3 + 3
TX = 0.3


@pytest.mark.mpi
def test_nodal_forces_partition_into_regions():
    from dolfinx import fem, mesh

    comm = MPI.COMM_WORLD
    msh = mesh.create_unit_cube(comm, N, N, N)
    top = np.sort(mesh.locate_entities_boundary(msh, 2, lambda x: np.isclose(x[2], 1.0)))
    mid = mesh.compute_midpoints(msh, 2, top)
    codes = np.where(mid[:, 0] < 0.5, INDEX_DISTAL, MIDDLE_DISTAL).astype(np.int32)
    ft = mesh.meshtags(msh, 2, top.astype(np.int32), codes)
    model = SimpleNamespace(mesh=msh, facet_tags=ft,
                            groups={"skin_outer": [INDEX_DISTAL, MIDDLE_DISTAL]})
    V = fem.VectorFunctionSpace(msh, ("CG", 1))
    u1 = fem.Function(V)
    f1 = fem.Function(V)
    f1.interpolate(lambda x: np.vstack([np.full(x.shape[1], TX), 0 * x[0],
                                        np.isclose(x[2], 1.0).astype(float)]))
    f1.x.array[:] *= np.repeat(np.isclose(V.tabulate_dof_coordinates()[:, 2], 1.0), 3)
    p1 = fem.Function(fem.FunctionSpace(msh, ("CG", 1)))
    plate = HalfSpace(point=(0.0, 0.0, 1.0), normal=(0.0, 0.0, -1.0))
    fd = facet_data(model, u1, p1, None, plate, np.zeros(3), 0.01, node_force=f1)
    r = region_metrics(fd, comm)
    n_top = (N + 1) ** 2  # top nodes, each pushing with (TX, 0, 1) N
    total = np.array(r["index"]["force_vector_N"]) + np.array(r["middle"]["force_vector_N"])
    assert total == pytest.approx([TX * n_top, 0.0, n_top], rel=1e-12, abs=1e-12)
    # the nodes on x = 1/2 are shared by both regions: 2 of their facets (of 6 or 3) on each
    # side; the partition is exact and the split is the normal/tangential one of the plate
    for reg in ("index", "middle"):
        fz = r[reg]["force_vector_N"][2]
        assert r[reg]["normal_force_N"] == pytest.approx(fz, rel=1e-12)
        assert r[reg]["tangential_force_N"] == pytest.approx(TX * fz, rel=1e-12)
        assert r[f"{reg}_distal"]["normal_force_N"] == pytest.approx(fz, rel=1e-12)
    assert r["index"]["force_vector_N"][2] == pytest.approx(n_top / 2, rel=1e-12)
    assert r["ring"]["normal_force_N"] == 0.0
    # every node loaded: the mean pressure is the total normal load over the face area (1 mm2)
    both = {k: r[k] for k in ("index", "middle")}
    load = sum(v["force_vector_N"][2] for v in both.values())
    assert load == pytest.approx(n_top)
    for v in both.values():
        assert v["mean_pressure_kPa"] == pytest.approx(1e3 * n_top, rel=1e-12)
        # an interior node carries 1 N on h^2 = 1/16 mm2; boundary nodes on less area
        assert v["peak_pressure_kPa"] >= 1e3 * N * N * (1 - 1e-12)
        # every node is pressed far above 10 kPa: each half of the face is loaded, on any
        # partition (owned facets only, summed over ranks)
        assert v["loaded_area_mm2"] == pytest.approx(0.5, rel=1e-12)


def test_mean_pressure_ignores_a_dust_of_tiny_nodal_forces():
    """Two facets pressed with 1 MPa at every vertex and eight with a numerical dust of
    1e-9 MPa: the mean pressure is 1 MPa (1000 kPa), not diluted by the dust's area."""
    nf = 10
    p = np.full((nf, 3), 1e-9)
    p[:2] = 1.0
    n = np.tile([0.0, 0.0, -1.0], (nf, 3, 1))  # object normal; pressing force along -n
    a_share = np.full((nf, 3), 1.0 / 3.0)  # mm2 per facet vertex
    f = p[..., None] * a_share[..., None] * -n  # force on the object (N)
    fd = {"codes": np.full(nf, INDEX_DISTAL), "p": p, "t": np.zeros((nf, 3, 3)), "n": n,
          "area_c": np.r_[np.ones(2), np.zeros(nf - 2)], "area": np.ones(nf), "f": f,
          "p_node": p, "a_share": a_share}
    r = region_metrics(fd, MPI.COMM_SELF)["index"]
    assert r["mean_pressure_kPa"] == pytest.approx(1000.0, rel=1e-6)
    assert r["contact_area_mm2"] == pytest.approx(2.0)
    # loaded area: a third of a facet per vertex at >= the threshold; the dust is not loaded
    assert r["loaded_area_mm2"] == pytest.approx(2.0)
    assert region_metrics(fd, MPI.COMM_SELF, loaded_area_kPa=1001.0)["index"][
        "loaded_area_mm2"] == 0.0
    # a pressed facet whose vertices all sit beyond gap_tol (a flat facet on a curved object):
    # its area is its loaded nodes' tributary share, not 0
    fd["area_c"] = np.zeros(nf)
    r = region_metrics(fd, MPI.COMM_SELF)["index"]
    assert r["contact_area_mm2"] == pytest.approx(2.0)
    assert r["mean_pressure_kPa"] == pytest.approx(1e3 * r["normal_force_N"]
                                                   / r["contact_area_mm2"], rel=1e-6)
    assert r["peak_pressure_kPa"] == pytest.approx(1000.0)
    assert r["normal_force_N"] == pytest.approx(2.0, rel=1e-6)


def _nodal_fd(p_MPa: np.ndarray, a_share: np.ndarray, codes: np.ndarray) -> dict:
    """Facet data of flat facets (normal -z) pressed with nodal pressures ``p_MPa`` (nf, 3)
    over the tributary shares ``a_share`` (nf, 3, mm2), none within gap_tol by its gap."""
    nf = len(codes)
    n = np.tile([0.0, 0.0, -1.0], (nf, 3, 1))
    return {"codes": codes, "p": p_MPa, "t": np.zeros((nf, 3, 3)), "n": n,
            "area_c": np.zeros(nf), "area": 3.0 * a_share.mean(axis=1),
            "f": p_MPa[..., None] * a_share[..., None] * -n, "p_node": p_MPa,
            "a_share": a_share}


def test_contact_area_holds_the_loaded_area_under_a_high_peak():
    """With a 2 MPa peak elsewhere on the skin, 1 % of the peak is 20 kPa: a pad pressed with
    15 kPa is still in contact, as it is loaded (>= 10 kPa). Before, the muscle-driven thumb
    was 'loaded' over 194 mm2 and 'in contact' over 157 mm2 (peak 1.3 MPa)."""
    p = np.array([[2.0, 2.0, 2.0], [0.015, 0.015, 0.015], [0.005, 0.005, 0.005]])
    codes = np.array([MIDDLE_DISTAL, INDEX_DISTAL, INDEX_DISTAL])
    r = region_metrics(_nodal_fd(p, np.ones((3, 3)), codes), MPI.COMM_SELF)["index"]
    assert r["loaded_area_mm2"] == pytest.approx(3.0)
    assert r["contact_area_mm2"] == pytest.approx(3.0)  # the 5 kPa facet is below both
    assert r["mean_pressure_kPa"] == pytest.approx(15.0)


@pytest.mark.parametrize("threshold_kPa", [1.0, 10.0, 100.0])
def test_loaded_area_never_exceeds_the_contact_area(threshold_kPa):
    """Random nodal pressures (70 % of the nodes 0, the rest 0-2 MPa) and tributary shares over
    facets of two digits and their segments: every region's loaded area is <= its contact
    area."""
    rng = np.random.default_rng(7)
    nf = 400
    p = rng.uniform(0.0, 2.0, (nf, 3)) * (rng.uniform(size=(nf, 3)) < 0.3)
    codes = rng.choice([INDEX_DISTAL, INDEX_DISTAL - 1, MIDDLE_DISTAL], nf)
    r = region_metrics(_nodal_fd(p, rng.uniform(0.1, 2.0, (nf, 3)), codes), MPI.COMM_SELF,
                       loaded_area_kPa=threshold_kPa)
    for k, v in r.items():
        assert v["loaded_area_mm2"] <= v["contact_area_mm2"] * (1 + 1e-12), k


def test_pressure_map_draws_loaded_facets_over_the_skin_in_front(tmp_path):
    """A loaded pad facing into the closed hand (behind unloaded skin in the palmar view) is
    still seen: its colour, not the skin's grey, fills the centre of the picture."""
    import matplotlib.image as mpimg

    from handfe.grasp.outputs import pressure_map_png

    tri = np.array([[-10.0, -10.0, 0.0], [10.0, -10.0, 0.0], [0.0, 10.0, 0.0]])
    xf = np.stack([tri + [0, 0, -5.0], tri + [0, 0, 5.0]])  # loaded behind, skin in front
    p = np.array([[0.1, 0.1, 0.1], [0.0, 0.0, 0.0]])  # MPa
    fd = {"xf": xf, "p": p, "codes": np.array([INDEX_DISTAL] * 2)}
    pressure_map_png(fd, np.eye(3), tmp_path / "p.png", MPI.COMM_SELF)
    img = mpimg.imread(tmp_path / "p.png")
    ax_px = img[:, : int(0.75 * img.shape[1])]  # left of the colour bar
    grey = np.all(np.abs(ax_px[..., :3] - 0.85) < 0.02, axis=-1)
    dark = np.all(ax_px[..., :3] < 0.3, axis=-1)  # 100 kPa = the top of inferno_r: near black
    assert dark.sum() > 20 * grey.sum()


def test_plot_redraws_a_run_pressure_map_on_a_given_scale(tmp_path, capsys):
    """``handfe plot RUN`` draws the map again from the facets the run kept, on the colour
    scale asked for: a 50 kPa pad on a 0-100 kPa scale is mid-scale, not the top colour."""
    import matplotlib.image as mpimg

    from handfe.cli import main
    from handfe.grasp.outputs import pressure_map_png

    tri = np.array([[[-10.0, -10.0, 0.0], [10.0, -10.0, 0.0], [0.0, 10.0, 0.0]]])
    fd = {"xf": tri, "p": np.full((1, 3), 0.05), "codes": np.array([INDEX_DISTAL])}
    pressure_map_png(fd, np.eye(3), tmp_path / "pressure.png", MPI.COMM_SELF, title="t",
                     facets_npz=tmp_path / "pressure_facets.npz")

    def dark_px(png):
        img = mpimg.imread(png)[:, : int(0.75 * mpimg.imread(png).shape[1])]
        return int(np.all(img[..., :3] < 0.3, axis=-1).sum())

    own = dark_px(tmp_path / "pressure.png")  # own scale: the pad is the top colour
    assert main(["plot", str(tmp_path), "--vmax", "100", "--out", str(tmp_path / "b.png")]) == 0
    assert "0-100 kPa" in capsys.readouterr().out
    assert dark_px(tmp_path / "b.png") < 0.2 * own  # the text and ticks stay dark


def test_plot_names_a_folder_without_facets(tmp_path, capsys):
    from handfe.cli import main

    assert main(["plot", str(tmp_path)]) != 0
    err = capsys.readouterr().err
    assert "pressure_facets.npz" in err and "not found" in err


def test_loaded_area_counts_a_third_of_a_facet_per_loaded_vertex():
    facet_area = np.array([3.0, 6.0, 1.0])
    p_kPa = np.array([[10.0, 9.99, 0.0], [50.0, 50.0, 50.0], [0.0, 0.0, 0.0]])
    assert loaded_area(facet_area, p_kPa, 10.0) == pytest.approx([1.0, 6.0, 0.0])


def test_handfe_run_ends_with_the_six_regions_table(tmp_path, monkeypatch, capsys):
    """After a run the command prints the six regions' rows of regions.csv (areas mm2,
    pressures kPa, forces N, in that column order), not the segments; --quiet prints none."""
    import handfe.grasp.scene as scene
    from handfe.cli import main
    from handfe.grasp.outputs import METRICS, region_table
    from handfe.grasp.scene import GraspResult

    regs = {r: dict(zip(METRICS, (100.0 + i, 50.0, 30.4, 166.6, 6.456, 0.66), strict=True))
            for i, r in enumerate(("thumb", "thumb_distal", "index", "middle", "ring",
                                   "little", "palm"))}
    table = region_table(regs).splitlines()
    assert table[0].split() == ["region", "contact", "mm2", "loaded", "mm2", "mean", "kPa",
                                "peak", "kPa", "normal", "N", "tangential", "N"]
    assert [row.split()[0] for row in table[1:]] == ["thumb", "index", "middle", "ring",
                                                     "little", "palm"]
    assert table[1].split() == ["thumb", "100", "50", "30", "167", "6.46", "0.66"]
    assert len({len(row) for row in table}) == 1  # fixed width
    pinch = region_table(regs, ["ring", "little"]).splitlines()
    assert [row.split()[0] for row in pinch[1:-1]] == ["thumb", "index", "middle", "palm"]
    assert pinch[-1] == "not meshed: ring, little"

    # patched where it lives: handfe.grasp hands it out lazily (module __getattr__), and a
    # patch of handfe.grasp.run_workflow would leave the real function bound there on undo,
    # where later tests' patches of scene.run_workflow no longer reach
    monkeypatch.setattr(scene, "run_workflow", lambda wf, **kw: GraspResult(
        regs, {"status": "done", "skipped": {"digits": ["ring", "little"]}}, tmp_path))
    assert main(["run", "precision", "--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "\n".join(pinch) in out and "regions.csv" in out
    assert main(["run", "precision", "--quiet", "--out", str(tmp_path)]) == 0
    assert "contact mm2" not in capsys.readouterr().out


def test_pressure_map_names_each_loaded_region_at_its_patch():
    """The map's labels: one per region with loaded facets (REGIONS order), at the
    pressure-weighted centroid of those facets; an unloaded region gets none."""
    from handfe.grasp.outputs import region_labels

    tri = np.array([[0.0, 0.0], [3.0, 0.0], [0.0, 3.0]])  # centroid (1, 1)
    xy = np.stack([tri, tri + [10.0, 0.0], tri + [0.0, 20.0], tri + [50.0, 50.0]])
    pf = np.array([30.0, 10.0, 5.0, 0.0])
    loaded = pf > 0.0
    reg = np.array(["index", "index", "thumb", "palm"])
    labels = region_labels(xy, pf, loaded, reg)
    assert [name for name, _, _ in labels] == ["thumb", "index"]
    assert labels[0][1:] == pytest.approx((1.0, 21.0))
    assert labels[1][1:] == pytest.approx((1.0 + 10.0 * 10 / 40, 1.0))
