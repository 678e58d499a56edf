"""Meshed hands (reduced level): tags, volumes, skin thickness, quality for the three grasp
postures, outputs and CLI errors. About 1-2 minutes on 2 busy cores (three gmsh meshes)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from mpi4py import MPI

from handfe.anatomy import build_hand, load_subject
from handfe.anatomy.meshing import CELL_TAGS, tag_names
from handfe.kinematics import DIGITS, Pose
from handfe.paths import ANATOMY_DIR, SUBJECTS_DIR

# Stated mesh-quality threshold (radius ratio 3 r_in / r_circ, 1 = regular tet), measured on the
# reduced meshes of the three grasp postures (min 0.001 - 0.011, a few dozen cells below 0.1
# out of ~100k, in the 1.2 mm skin layer at creases; gmsh HXT, Debian's gmsh 4.8 has no Netgen).
MIN_QUALITY = 5e-4
MAX_FRACTION_BELOW_0_1 = 2e-3
POSES = {g: ANATOMY_DIR / "poses" / f"{g}.toml" for g in ("cylindrical", "spherical",
                                                          "precision")}


@pytest.fixture(scope="module")
def subject():
    return load_subject(SUBJECTS_DIR / "S01")


@pytest.fixture(scope="module")
def cylindrical(subject):
    return build_hand(subject, Pose.from_toml(POSES["cylindrical"]), level="reduced",
                      comm=MPI.COMM_SELF)


@pytest.fixture(scope="module")
def pinch(subject):
    """Partial hand without the far-field savings (carpus and wrist kept, uniform sizes); the
    default trimmed pinch is tested in tests/test_anatomy_partial.py."""
    return build_hand(subject, Pose.from_toml(POSES["precision"]),
                      digits="thumb,index,middle", level="reduced", comm=MPI.COMM_SELF,
                      skip_far=False)


@pytest.fixture(scope="module")
def spherical(subject):
    return build_hand(subject, Pose.from_toml(POSES["spherical"]), level="reduced",
                      comm=MPI.COMM_SELF)


def _check_tags(model, digits, wrist=True):
    """Every tag present and non-empty (the wrist face only if ``wrist``: a trimmed partial
    hand has its proximal cut tagged palm_cut instead)."""
    tags, _ = tag_names(digits)
    cv = set(np.unique(model.cell_tags.values))
    assert cv == {CELL_TAGS["skin"], CELL_TAGS["subcutaneous"], CELL_TAGS["nail"]}
    fv = set(np.unique(model.facet_tags.values))
    for name, tag in tags.items():
        if name.startswith("skin_") or (name == "wrist" and wrist):
            assert tag in fv, name
    for b in model.bones:
        assert model.tags[f"bone_{b}"] in fv, b
    # bone surfaces are cavities: each bone facet touches exactly one cell, a subcutaneous one
    msh = model.mesh
    tdim = msh.topology.dim
    msh.topology.create_connectivity(tdim - 1, tdim)
    f2c = msh.topology.connectivity(tdim - 1, tdim)
    cell_val = np.zeros(msh.topology.index_map(tdim).size_local, dtype=np.int32)
    cell_val[model.cell_tags.indices] = model.cell_tags.values
    bone_tags = set(model.groups["bones"])
    for f, v in zip(model.facet_tags.indices, model.facet_tags.values, strict=True):
        if v in bone_tags:
            cells = f2c.links(f)
            assert len(cells) == 1 and cell_val[cells[0]] == CELL_TAGS["subcutaneous"]


def _check_quality(model):
    q = model.quality
    assert q["min_quality"] > MIN_QUALITY
    assert q["cells_quality_below_0.1"] / q["cells"] < MAX_FRACTION_BELOW_0_1
    assert q["min_dihedral_angle_deg"] > 0.0
    t = q["skin_thickness_mm"]
    assert t["n_points"] >= 20
    assert 0.9 * t["nominal"] <= t["min"] and t["max"] <= 1.1 * t["nominal"]
    for v in q["volume_mm3"].values():
        assert v > 0


def test_whole_hand_cylindrical(cylindrical):
    m = cylindrical
    assert m.digits == DIGITS
    assert len(m.bones) == 27
    assert m.quality["skipped"]["digits"] == [] and m.quality["skipped"]["bones"] == []
    _check_tags(m, DIGITS)
    _check_quality(m)
    q = m.quality
    assert 300.0 <= q["hand_volume_cm3"] <= 600.0
    a = q["skin_area_mm2"]
    assert all(a[r] > 0 for r in ("thumb", "index", "middle", "ring", "little", "palm"))
    assert a["palm"] > a["middle"] > a["little"]
    # nail on every distal phalanx, much thinner than the whole skin
    assert 0 < q["volume_mm3"]["nail"] < 0.05 * q["volume_mm3"]["skin"]


def test_facet_tags_agree_with_gmsh_areas(cylindrical):
    import ufl
    from dolfinx import fem

    m = cylindrical
    ds = ufl.Measure("ds", domain=m.mesh, subdomain_data=m.facet_tags)
    one = fem.Constant(m.mesh, 1.0)
    area = fem.assemble_scalar(fem.form(one * ds(m.groups["index"])))
    assert area == pytest.approx(m.quality["skin_area_mm2"]["index"], rel=0.02)
    wrist = fem.assemble_scalar(fem.form(one * ds(m.tags["wrist"])))
    h = m.skeleton.subject.hand
    assert 0.5 * h.wrist_breadth_mm * h.wrist_thickness_mm < wrist < (
        h.wrist_breadth_mm * h.wrist_thickness_mm)


def test_spherical_quality(spherical):
    _check_tags(spherical, DIGITS)
    _check_quality(spherical)


def test_pinch_only_mesh(pinch, cylindrical):
    """skip_far=False: only the dropped rays and the palm part carrying them are left out
    (70.7k vs 107k tets); the default (trimmed) pinch is ~0.37x, tests/test_anatomy_partial.py."""
    digits = ("thumb", "index", "middle")
    assert pinch.digits == digits
    _check_tags(pinch, digits)
    _check_quality(pinch)
    assert pinch.tags["palm_cut"] in set(np.unique(pinch.facet_tags.values))
    assert not any(b.startswith(("ring", "little")) for b in pinch.bones)
    assert pinch.quality["cells"] < 0.75 * cylindrical.quality["cells"]
    assert pinch.quality["skin_area_mm2"]["ring"] == 0.0
    sk = pinch.quality["skipped"]
    assert sk["digits"] == ["ring", "little"]
    assert set(sk["bones"]) == set(pinch.skeleton.bones) - set(pinch.bones)
    assert {"scaphoid", "lunate", "trapezium", "capitate"} <= set(pinch.bones)
    # ligaments and insertions restricted to the kept bones
    kept = set(pinch.bones)
    assert all(lg["bone_a"] in kept and lg["bone_b"] in kept for lg in pinch.ligaments)
    assert {i["muscle"] for i in pinch.insertions} == {"FDS", "FDP", "APL", "APB", "AP",
                                                       "FPB", "FDI", "SDI", "TDI"}


def test_outputs(pinch, tmp_path):
    from handfe.anatomy import write_outputs

    paths = write_outputs(pinch, tmp_path / "out")
    for p in paths.values():
        assert p.is_file() and p.stat().st_size > 0
    a = json.loads(paths["anatomy"].read_text())
    assert set(a["bones"]) == set(pinch.bones)
    M = np.array(a["bones"]["index_dp"]["frame"])
    assert np.allclose(M, pinch.skeleton.bones["index_dp"].frame.matrix())
    assert a["joints"]["index_pip"]["dofs"]["index_pip_flexion"]["value"] == 50.0
    q = json.loads(paths["quality"].read_text())
    assert q["cells"] == pinch.quality["cells"]
    assert (tmp_path / "out" / "hand.h5").is_file()


def test_cli_errors(tmp_path, capsys):
    from handfe.cli import main

    bad = tmp_path / "bad.toml"
    bad.write_text("[angles]\nindex_pip_flexion = 130.0\n")
    assert main(["anatomy", "--pose", str(bad), "--out", str(tmp_path / "o")]) == 2
    assert "index_pip_flexion = 130 deg is outside" in capsys.readouterr().err
    assert main(["anatomy", "--digits", "thumb,pinky", "--out", str(tmp_path / "o")]) == 2
    assert "unknown digit 'pinky'" in capsys.readouterr().err
    assert main(["anatomy", "--digits", "index,ring", "--out", str(tmp_path / "o")]) == 2
    assert "neighbours" in capsys.readouterr().err


def test_import_round_trip(pinch, tmp_path):
    from handfe.anatomy.importer import export_surfaces, import_hand

    skin, bones_dir = export_surfaces(pinch, tmp_path / "scan")
    m = import_hand(skin, bones_dir, skin_thickness_mm=1.2, comm=MPI.COMM_SELF)
    assert set(m.bones) == set(pinch.bones)
    fv = set(np.unique(m.facet_tags.values))
    for b in m.bones:
        assert m.tags[f"bone_{b}"] in fv
    for name in ("skin_index_distal", "skin_middle_proximal", "skin_thumb_distal", "skin_palm"):
        assert m.tags[name] in fv
    assert set(np.unique(m.cell_tags.values)) == {1, 2}
    # same hand: enclosed volume within 2 %
    assert m.quality["hand_volume_cm3"] == pytest.approx(pinch.quality["hand_volume_cm3"],
                                                         rel=0.02)
    assert m.quality["min_quality"] > MIN_QUALITY
    from handfe.anatomy import write_outputs

    paths = write_outputs(m, tmp_path / "imported")
    assert paths["png"].is_file()


def test_import_refusals(pinch, tmp_path):
    import trimesh

    from handfe.anatomy.importer import export_surfaces, import_hand, load_surface
    from handfe.errors import InputError

    skin, bones_dir = export_surfaces(pinch, tmp_path / "scan")
    m = trimesh.load(skin, force="mesh")
    one = tmp_path / "one_missing.stl"
    trimesh.Trimesh(m.vertices, m.faces[:-1], process=False).export(one)
    repaired = load_surface(one, "skin surface")  # a single missing triangle is repaired
    assert repaired.is_watertight and repaired.volume == pytest.approx(m.volume, rel=1e-3)
    holed = trimesh.Trimesh(m.vertices, m.faces[:-40], process=False)
    bad = tmp_path / "holed.stl"
    holed.export(bad)
    with pytest.raises(InputError, match=r"holed.stl: the skin surface is not watertight"):
        load_surface(bad, "skin surface")
    (bones_dir / "femur.stl").write_bytes((bones_dir / "index_dp.stl").read_bytes())
    with pytest.raises(InputError, match="unknown bone name 'femur'"):
        import_hand(skin, bones_dir, comm=MPI.COMM_SELF)
    (bones_dir / "femur.stl").unlink()
    b = trimesh.load(bones_dir / "index_dp.stl", force="mesh")
    b.apply_translation([0.0, 0.0, -30.0])  # push the bone out of the finger
    b.export(bones_dir / "index_dp.stl")
    with pytest.raises(InputError, match="bone index_dp is not inside"):
        import_hand(skin, bones_dir, comm=MPI.COMM_SELF)


@pytest.mark.mpi
def test_distributed_mesh_matches_gmsh_volumes(subject):
    """Under mpirun -n 2: gmsh runs on rank 0, the mesh is distributed, and the volumes
    assembled over all ranks equal the serial gmsh report."""
    import ufl
    from dolfinx import fem

    comm = MPI.COMM_WORLD
    m = build_hand(subject, Pose.neutral(), digits="index,middle", level="reduced", comm=comm)
    dx = ufl.Measure("dx", domain=m.mesh, subdomain_data=m.cell_tags)
    one = fem.Constant(m.mesh, 1.0)
    for name in ("skin", "subcutaneous", "nail"):
        v = comm.allreduce(fem.assemble_scalar(fem.form(one * dx(m.tags[name]))), op=MPI.SUM)
        assert v == pytest.approx(m.quality["volume_mm3"][name], rel=1e-6)
    n_cells = comm.allreduce(m.mesh.topology.index_map(3).size_local, op=MPI.SUM)
    assert n_cells == m.quality["cells"]


def test_hand_meshing_leaves_no_gmsh_options_behind():
    """gmsh options are global and outlive the model: the hand's Mesh.MeshSizeMax (a few mm)
    once capped the next mesher's 40 mm elements (the Hertz block after the pinch test in the
    CI's MPI phase: 289,836 cells instead of 2,784)."""
    import gmsh

    from handfe.anatomy.meshing import ensure_gmsh, release_gmsh, skin_surface
    from handfe.grasp.mechanics import opened_pose
    from handfe.kinematics import grasp_pose

    sd = SUBJECTS_DIR / "S01"
    digits = ("thumb", "index", "middle")
    skin_surface(load_subject(sd), opened_pose(grasp_pose(sd, "precision"), digits, 5.0),
                 digits=digits, level="coarse", comm=MPI.COMM_SELF)
    ensure_gmsh(gmsh)
    try:
        assert gmsh.option.getNumber("Mesh.MeshSizeMax") == pytest.approx(1e22)
    finally:
        release_gmsh(gmsh)
