"""Partial hands that skip what a pinch does not need (carpus and wrist cut away, coarse far
from the kept digits) and the `coarse` mesh level (whole hand, cylindrical posture).

Two gmsh meshes: the pinch (reduced, ~39k tets) and the coarse whole hand (~43k tets); about
45-80 s on 2 cores shared with other jobs."""

from __future__ import annotations

import numpy as np
import pytest
from mpi4py import MPI

from handfe.anatomy import build_hand, load_subject
from handfe.anatomy.meshing import CELL_TAGS, LEVELS, WHOLE_HAND_CELLS_S01, tag_names
from handfe.errors import InputError
from handfe.kinematics import DIGITS, Pose
from handfe.paths import ANATOMY_DIR, SUBJECTS_DIR

# the quality threshold stated in tests/test_anatomy_mesh.py (radius ratio 3 r_in / r_circ)
MIN_QUALITY = 5e-4
MAX_FRACTION_BELOW_0_1 = 2e-3


@pytest.fixture(scope="module")
def subject():
    return load_subject(SUBJECTS_DIR / "S01")


@pytest.fixture(scope="module")
def coarse(subject):
    return build_hand(subject, Pose.from_toml(ANATOMY_DIR / "poses" / "cylindrical.toml"),
                      level="coarse", comm=MPI.COMM_SELF)


@pytest.fixture(scope="module")
def pinch(subject):
    return build_hand(subject, Pose.from_toml(ANATOMY_DIR / "poses" / "precision.toml"),
                      digits="thumb,index,middle", level="reduced", comm=MPI.COMM_SELF)


def test_pinch_mesh_is_small(pinch):
    """The default pinch mesh is <= 0.4x the whole hand at the same level. Measured (S01,
    reduced, 22 Nov 2026): `handfe anatomy --pose anatomy/poses/precision.toml --digits
    thumb,index,middle --out results/anatomy/pinch` -> ~39k tets, against 106.7k for the
    whole hand in the same posture (`handfe anatomy --pose anatomy/poses/precision.toml --out
    results/anatomy/prec`) and 105.9k neutral (WHOLE_HAND_CELLS_S01, the stored reference):
    about 0.37x."""
    q = pinch.quality
    assert q["cells"] <= 0.4 * WHOLE_HAND_CELLS_S01["reduced"]
    sk = q["skipped"]
    assert sk["digits"] == ["ring", "little"]
    assert sk["cells_whole_hand_estimate"] == WHOLE_HAND_CELLS_S01["reduced"]  # S01 scale 1
    assert sk["cells_saved_estimate"] == sk["cells_whole_hand_estimate"] - q["cells"] > 0
    assert sk["fraction_of_whole_hand"] <= 0.4
    assert set(sk["bones"]) == set(pinch.skeleton.bones) - set(pinch.bones)
    assert any("carpus" in r for r in sk["regions"])
    # ligaments of dropped bones are listed; those from a kept bone to a cut-away carpal (a
    # fixed point in the hand frame) separately, e.g. the thumb CMC ligaments to the trapezium
    assert {"thumb_cmc_aol", "thumb_cmc_drl", "thumb_cmc_pol"} <= set(
        sk["ligaments_to_dropped_carpals"]) <= set(sk["ligaments"])
    assert not {lg["name"] for lg in pinch.ligaments} & set(sk["ligaments"])


def test_pinch_tags_and_quality(pinch):
    """Every tag of the kept digits present and non-empty; the carpus cut is tagged palm_cut
    (91) and there is no wrist face (90); quality and skin thickness as for the whole hand."""
    from handfe.anatomy.tables import CARPALS

    m = pinch
    digits = ("thumb", "index", "middle")
    assert m.digits == digits
    assert set(np.unique(m.cell_tags.values)) == set(CELL_TAGS.values())
    fv = set(np.unique(m.facet_tags.values))
    tags, _ = tag_names(digits)
    for name, tag in tags.items():
        if name.startswith(("skin_", "bone_")) and (not name.startswith("bone_")
                                                   or name[5:] in m.bones):
            assert tag in fv, name
    assert tags["palm_cut"] in fv and tags["wrist"] not in fv
    assert {"thumb_mc", "index_mc", "middle_mc", "thumb_dp", "index_dp"} <= set(m.bones)
    assert not set(CARPALS) & set(m.bones)
    assert not any(b.startswith(("ring", "little")) for b in m.bones)
    q = m.quality
    assert q["min_quality"] > MIN_QUALITY
    assert q["cells_quality_below_0.1"] / q["cells"] < MAX_FRACTION_BELOW_0_1
    t = q["skin_thickness_mm"]
    assert t["n_points"] >= 20
    assert 0.9 * t["nominal"] <= t["min"] and t["max"] <= 1.1 * t["nominal"]
    assert all(v > 0 for v in q["volume_mm3"].values())
    # the pads keep their fine size; the far field is coarser than h
    assert q["mesh_sizes_mm"]["h_far"] > q["mesh_sizes_mm"]["h"]
    # muscles acting on the kept rays keep their insertions
    assert {i["muscle"] for i in m.insertions} == {"FDS", "FDP", "APL", "APB", "AP", "FPB",
                                                  "FDI", "SDI", "TDI"}


def test_coarse_level_listed():
    assert list(LEVELS) == ["coarse", "reduced", "default", "fine"]
    assert LEVELS["coarse"]["h"] > LEVELS["reduced"]["h"]


def test_coarse_whole_hand(coarse):
    """Measured (S01, cylindrical, `handfe anatomy --pose anatomy/poses/cylindrical.toml
    --mesh coarse --out results/anatomy/coarse`, 22 Nov 2026): ~43k tets vs ~107k reduced,
    min quality ~0.008, ~0.14 % of cells below 0.1 (same threshold as the reduced meshes)."""
    m = coarse
    q = m.quality
    assert m.level == "coarse" and m.digits == DIGITS and len(m.bones) == 27
    assert q["cells"] <= 50_000
    # quality above the threshold the reduced-mesh tests state
    assert q["min_quality"] > MIN_QUALITY
    assert q["cells_quality_below_0.1"] / q["cells"] < MAX_FRACTION_BELOW_0_1
    assert q["min_dihedral_angle_deg"] > 0.0
    # every tag present and non-empty
    assert set(np.unique(m.cell_tags.values)) == set(CELL_TAGS.values())
    fv = set(np.unique(m.facet_tags.values))
    tags, groups = tag_names(DIGITS)
    assert tags["palm_cut"] not in fv  # the whole hand has no palm cut
    for name, tag in tags.items():
        if name.startswith(("skin_", "bone_")) or name == "wrist":
            assert tag in fv, name
    # same hand as the finer levels: volume and areas plausible
    assert 300.0 <= q["hand_volume_cm3"] <= 600.0
    assert all(v > 0 for v in q["volume_mm3"].values())
    assert all(q["skin_area_mm2"][r] > 0 for r in ("thumb", "index", "middle", "ring",
                                                    "little", "palm"))
    # the skin layer is still a separate volume (>= 1 element through its thickness); its CAD
    # thickness is exact, but 4.7 mm chords of the inner surface on the thin digits make the
    # mesh's layer locally thicker (measured max 1.20-1.79 mm for 1.2 mm, depending on pose)
    t = q["skin_thickness_mm"]
    assert 0.9 * t["nominal"] <= t["min"] and t["max"] <= 1.6 * t["nominal"]
    assert q["skipped"]["digits"] == [] and q["skipped"]["cells_saved_estimate"] == 0


def test_coarse_facet_areas_match_gmsh(coarse):
    import ufl
    from dolfinx import fem

    m = coarse
    ds = ufl.Measure("ds", domain=m.mesh, subdomain_data=m.facet_tags)
    one = fem.Constant(m.mesh, 1.0)
    for region in ("thumb", "palm"):
        area = fem.assemble_scalar(fem.form(one * ds(m.groups[region])))
        assert area == pytest.approx(m.quality["skin_area_mm2"][region], rel=0.02)


def test_skip_far_needs_partial_hand(subject):
    with pytest.raises(InputError, match="skip_far needs a partial hand"):
        build_hand(subject, Pose.neutral(), skip_far=True, comm=MPI.COMM_SELF)
    with pytest.raises(InputError, match="mesh level 'tiny'"):
        build_hand(subject, Pose.neutral(), level="tiny", comm=MPI.COMM_SELF)


def test_cli_coarse_and_skip_options(tmp_path, capsys):
    from handfe.cli import main

    with pytest.raises(SystemExit):
        main(["anatomy", "--help"])
    out = capsys.readouterr().out
    assert "coarse" in out and "--no-skip-far" in out
    assert main(["anatomy", "--no-skip-far", "--out", str(tmp_path / "o")]) == 2
    assert "--no-skip-far is only used with --digits" in capsys.readouterr().err


def test_partial_bones_and_planes(subject):
    """No meshing: which bones a trimmed pinch keeps and where the proximal cut lies."""
    from handfe.anatomy.geometry import TRIM_MARGIN_MM, cut_planes, kept_bones
    from handfe.anatomy.skeleton import build_skeleton
    from handfe.anatomy.tables import CARPALS

    sk = build_skeleton(subject, Pose.from_toml(ANATOMY_DIR / "poses" / "precision.toml"))
    digits = ("thumb", "index", "middle")
    planes = cut_planes(sk, digits, trim_carpus=True)
    assert len(planes) == 2  # ulnar side cut + proximal (carpus) cut
    kept = kept_bones(sk, digits, planes)
    assert {"thumb_mc", "index_mc", "middle_mc", "index_dp", "thumb_dp"} <= set(kept)
    assert not set(CARPALS) & set(kept)
    assert not any(b.startswith(("ring", "little")) for b in kept)
    # the proximal plane: normal to the hand's y axis, proximal to every kept CMC centre by at
    # least the margin, distal to the wrist crease, clear of every kept bone by skin + 1.5 mm
    p0, n = planes[-1]
    H = sk.hand_frame
    assert np.allclose(n, -H.R[:, 1])
    y_cut = H.inverse_apply(p0)[1]
    y_cmc = min(H.inverse_apply(sk.joint_centres[f"{d}_cmc"])[1] for d in digits)
    assert 0.0 < y_cut <= y_cmc - TRIM_MARGIN_MM + 1e-9
    clear = sk.subject.hand.skin_thickness_mm + 1.5
    for b in kept:
        e = sk.bones[b].ellipsoid
        support = float(np.linalg.norm((e.R.T @ n) * e.s))
        assert float(np.dot(e.c - p0, n)) <= -support - clear + 1e-9
    # without the trim the carpus is kept (only the side cut drops the ulnar carpals)
    kept0 = kept_bones(sk, digits, cut_planes(sk, digits))
    assert {"scaphoid", "lunate", "trapezium", "capitate"} <= set(kept0)
