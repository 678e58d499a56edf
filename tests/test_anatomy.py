"""Anatomy tables, subject loading and forward kinematics (fast: no meshing)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from handfe.anatomy import build_skeleton, load_subject
from handfe.anatomy.skeleton import check_bones, rot
from handfe.anatomy.tables import (
    CARPALS,
    DIGIT_BONES,
    MUSCLES,
    bones,
    insertions,
    ligament_force_N,
    ligaments,
)
from handfe.errors import ConfigError, InputError
from handfe.kinematics import DIGITS, Pose, joint_table
from handfe.paths import ANATOMY_DIR, SUBJECTS_DIR

S01 = SUBJECTS_DIR / "S01"
POSES = {g: ANATOMY_DIR / "poses" / f"{g}.toml" for g in ("cylindrical", "spherical",
                                                          "precision")}


@pytest.fixture(scope="module")
def subject():
    return load_subject(S01)


def test_bone_table_has_the_27_bones():
    t = bones()
    assert len(t) == 27
    kinds = [b.kind for b in t.values()]
    assert kinds.count("phalanx") == 14 and kinds.count("metacarpal") == 5
    assert kinds.count("carpal") == 8 and set(CARPALS) <= set(t)
    joints = {d.joint for d in joint_table().values()}
    for b in t.values():
        assert b.parent_joint in joints, b.bone
        if b.kind != "carpal":
            assert 0.05 < b.length_frac < 0.4 and 0.03 < b.width_frac < 0.2


def test_ligaments_and_insertions():
    t = bones()
    ligs = ligaments()
    assert len(ligs) == 68
    assert len({lg.name for lg in ligs}) == 68
    for lg in ligs:
        assert lg.bone_a in t and lg.bone_b in t and lg.bone_a != lg.bone_b
        assert lg.k_N_per_mm > 0 and 0 < lg.eps_toe < 0.2 and lg.source
    ins = insertions()
    assert {i.muscle for i in ins} == set(MUSCLES)
    for m in MUSCLES:
        assert sum(i.share for i in ins if i.muscle == m) == pytest.approx(1.0)
    assert {i.bone for i in ins if i.muscle == "FDP"} == {f"{d}_dp" for d in DIGITS[1:]}
    assert {i.bone for i in ins if i.muscle == "FDS"} == {f"{d}_mp" for d in DIGITS[1:]}


def test_ligament_law_slack_toe_linear():
    L0, k, et = 10.0, 30.0, 0.06
    assert ligament_force_N(9.0, L0, k, et) == 0.0
    # continuous value and slope at the end of the toe region
    e = et * L0
    f_lo, f_hi = ligament_force_N(L0 + e - 1e-7, L0, k, et), ligament_force_N(L0 + e + 1e-7,
                                                                                 L0, k, et)
    assert f_hi == pytest.approx(f_lo, abs=1e-5)
    slope = (ligament_force_N(L0 + e + 0.1, L0, k, et) - ligament_force_N(L0 + e, L0, k, et)) / 0.1
    assert slope == pytest.approx(k)


def test_subject_S01(subject):
    h = subject.hand
    assert h.hand_length_mm == 189.0 and h.skin_thickness_mm == pytest.approx(1.2)
    assert len(subject.digit("thumb").segment_lengths_mm) == 3
    assert len(subject.digit("index").segment_lengths_mm) == 4
    # segment lengths are the Buchholz ratios times the hand length
    t = bones()
    for d in DIGITS:
        for b, L in zip(DIGIT_BONES[d], subject.digit(d).segment_lengths_mm, strict=True):
            assert L == pytest.approx(t[b].length_frac * h.hand_length_mm, abs=0.05)
    assert subject.fingertip.width_mm == pytest.approx(16.7)


def test_subject_rejects_unknown_keys_and_bad_values(tmp_path: Path):
    p = tmp_path / "anthropometry.toml"
    p.write_text("[hand]\nhand_length_mm = 189.0\nfinger_count = 5\n")
    with pytest.raises(ConfigError, match="finger_count"):
        load_subject(tmp_path)
    p.write_text("[hand]\nhand_length_mm = 500.0\n")
    with pytest.raises(ConfigError, match="hand.hand_length_mm.*500"):
        load_subject(tmp_path)
    p.write_text("[digits.index]\nsegment_lengths_mm = [70.0, 50.0, 27.0]\n")
    with pytest.raises(ConfigError, match="expected 4 values"):
        load_subject(tmp_path)
    # a minimal subject scales everything else from the tables
    p.write_text("[hand]\nhand_length_mm = 170.0\nhand_breadth_mm = 78.0\n")
    s = load_subject(tmp_path)
    assert s.digit("middle").segment_lengths_mm[1] == pytest.approx(0.277 * 170.0, abs=0.01)
    with pytest.raises(ConfigError, match="not found"):
        load_subject(tmp_path / "nowhere")


def test_zero_angles_give_the_neutral_pose(subject):
    zero = {n: d.neutral for n, d in joint_table().items()}
    a = build_skeleton(subject, Pose.neutral())
    b = build_skeleton(subject, Pose(zero))
    for n in a.bones:
        assert np.array_equal(a.bones[n].frame.matrix(), b.bones[n].frame.matrix())
    # neutral: fingers straight along their ray, hand frame = world frame
    assert np.allclose(a.hand_frame.matrix(), np.eye(4))
    for d in ("index", "middle", "ring", "little"):
        R = [a.segment_frames[x].R for x in DIGIT_BONES[d]]
        for Ri in R[1:]:
            assert np.allclose(Ri, R[0], atol=1e-12)


def _fk_index_distal(subject, pose: Pose) -> np.ndarray:
    """Independent forward kinematics of the index distal phalanx frame (4x4)."""
    from handfe.anatomy.skeleton import digit_base_frame

    def T(R, o=(0, 0, 0)):
        M = np.eye(4)
        M[:3, :3] = R
        M[:3, 3] = o
        return M

    ex, ey, ez = np.eye(3)
    W = T(rot(-ey, pose["wrist_pronation"]) @ rot(ex, pose["wrist_flexion"])
          @ rot(ez, pose["wrist_deviation"]),
          (pose["wrist_tx"], pose["wrist_ty"], pose["wrist_tz"]))
    base = digit_base_frame(subject, "index")
    L = subject.digit("index").segment_lengths_mm
    M = W @ T(base.R, base.o)
    M = M @ T(np.eye(3), (0, L[0], 0)) @ T(rot(ez, -pose["index_mcp_abduction"])
                                           @ rot(ex, pose["index_mcp_flexion"]))
    M = M @ T(np.eye(3), (0, L[1], 0)) @ T(rot(ex, pose["index_pip_flexion"]))
    M = M @ T(np.eye(3), (0, L[2], 0)) @ T(rot(ex, pose["index_dip_flexion"]))
    return M


@pytest.mark.parametrize("grasp", sorted(POSES))
def test_posed_frames_equal_forward_kinematics(subject, grasp):
    pose = Pose(dict(Pose.from_toml(POSES[grasp]).values, wrist_pronation=20.0,
                     wrist_tx=5.0, wrist_tz=-3.0))
    sk = build_skeleton(subject, pose)
    M = sk.bones["index_dp"].frame.matrix()
    assert np.max(np.abs(M - _fk_index_distal(subject, pose))) < 1e-9
    for b in sk.bones.values():  # proper rotations
        R = b.frame.R
        assert np.allclose(R.T @ R, np.eye(3), atol=1e-12)
        assert np.linalg.det(R) == pytest.approx(1.0)
    # joint centres sit at the distal end of the parent segment
    for d in DIGITS:
        names = DIGIT_BONES[d]
        L = subject.digit(d).segment_lengths_mm
        for k in range(1, len(names)):
            end = sk.segment_frames[names[k - 1]].apply(np.array([0.0, L[k - 1], 0.0]))
            assert np.allclose(end, sk.segment_frames[names[k]].o, atol=1e-9)


def test_sign_conventions(subject):
    def tip(sk, d):
        H = sk.hand_frame
        return H.inverse_apply(sk.bones[f"{d}_dp"].ellipsoid.c)

    n = build_skeleton(subject)
    flexed = build_skeleton(subject, Pose({"index_mcp_flexion": 30.0}))
    assert tip(flexed, "index")[2] > tip(n, "index")[2] + 10  # flexion: palmar (+z)
    ab = build_skeleton(subject, Pose({"index_mcp_abduction": 15.0, "little_mcp_abduction": 15.0,
                                       "thumb_cmc_abduction": 30.0}))
    assert tip(ab, "index")[0] > tip(n, "index")[0] + 5  # index: radial (+x)
    assert tip(ab, "little")[0] < tip(n, "little")[0] - 5  # little: ulnar
    assert tip(ab, "thumb")[2] > tip(n, "thumb")[2] + 5  # thumb: palmar abduction
    wf = build_skeleton(subject, Pose({"wrist_flexion": 30.0}))
    assert wf.bones["middle_dp"].ellipsoid.c[2] > n.bones["middle_dp"].ellipsoid.c[2] + 50


@pytest.mark.parametrize("grasp", ["neutral", *sorted(POSES), "finger_limits",
                                   "thumb_limits", "extension_limits", "abduction_limits"])
def test_bones_do_not_intersect(subject, grasp):
    def at(which, digits, axis="flexion"):
        return Pose({n: getattr(d, which) for n, d in joint_table().items()
                     if d.kind == "rotation" and d.digit in digits and d.axis == axis})

    if grasp == "neutral":
        pose = Pose.neutral()
    elif grasp == "finger_limits":  # fist: every finger joint at its flexion (max) limit
        pose = at("max", ("index", "middle", "ring", "little"))
    elif grasp == "thumb_limits":  # thumb fully flexed and abducted, fingers straight
        pose = Pose({**at("max", ("thumb",)).values,
                     **at("max", ("thumb",), "abduction").values})
    elif grasp == "extension_limits":  # every digit joint at its extension (min) limit
        pose = at("min", DIGITS)
    elif grasp == "abduction_limits":  # fingers spread to their abduction limits
        pose = at("max", DIGITS, "abduction")
    else:
        pose = Pose.from_toml(POSES[grasp])
    check_bones(build_skeleton(subject, pose))  # raises InputError on overlap


def test_bad_input():
    with pytest.raises(InputError, match="index_pip_flexion.*outside"):
        Pose({"index_pip_flexion": 150.0})
    from handfe.anatomy.meshing import parse_digits

    with pytest.raises(InputError, match="unknown digit 'pinky'"):
        parse_digits("thumb,pinky")
    from handfe.anatomy.geometry import cut_planes

    sk = build_skeleton(load_subject(S01))
    with pytest.raises(InputError, match="neighbours"):
        cut_planes(sk, ("index", "ring"))


def test_ligaments_and_insertions_posed(subject):
    sk = build_skeleton(subject, Pose.from_toml(POSES["cylindrical"]))
    ligs = sk.ligaments()
    assert len(ligs) == 68
    for lg in ligs:
        assert lg["length_mm"] > 0 and lg["slack_length_mm"] > 0
    # flexion stretches the dorsal side less than ... at least the PIP volar plate shortens
    vp = [lg for lg in ligs if lg["name"] == "index_pip_vp"][0]
    assert vp["length_mm"] < vp["slack_length_mm"]
    ins = sk.insertions()
    assert len(ins) == 15
    for i in ins:
        assert np.linalg.norm(i["direction"]) == pytest.approx(1.0)
    fdp = [i for i in ins if i["muscle"] == "FDP" and i["digit"] == "index"][0]
    # FDP pulls the distal phalanx proximally (towards the middle phalanx)
    F = sk.bones["index_dp"].frame
    assert np.dot(fdp["direction"], F.R[:, 1]) < 0
