"""Joint table, Pose and data-glove processing (handfe.kinematics, ``handfe angles``)."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest

from handfe import kinematics as kin
from handfe.cli import main
from handfe.errors import InputError
from handfe.paths import SUBJECTS_DIR

S01 = SUBJECTS_DIR / "S01"
GRASPS = ("cylindrical", "spherical", "precision")
UNMEASURED = {"wrist_pronation", "wrist_tx", "wrist_ty", "wrist_tz", "thumb_mcp_abduction",
              "middle_mcp_abduction"}


def _truth(path: Path) -> dict[str, float]:
    with path.open() as fh:
        return {r["dof"]: float(r["angle_deg"])
                for r in csv.DictReader(ln for ln in fh if not ln.startswith("#"))}


# ----------------------------------------------------------------------------- API kept

def test_joint_table_and_pose_api_backward_compatible(tmp_path):
    table = kin.joint_table()
    assert len(table) == 27 and kin.DIGITS[0] == "thumb"
    assert isinstance(table["index_pip_flexion"], kin.Dof)
    p = kin.Pose.neutral()
    assert p["index_pip_flexion"] == 0.0 and len(p.as_dict()) == 27
    with pytest.raises(KeyError):
        p["elbow"]
    q = kin.Pose({"index_pip_flexion": 45.0, "wrist_tx": 12.5}, source="t")
    f = q.write_toml(tmp_path / "pose.toml", description='a "quoted" pose')
    back = kin.Pose.from_toml(f)
    assert back.as_dict() == pytest.approx(q.as_dict())
    with pytest.raises(InputError, match="outside the joint limits"):
        kin.Pose({"index_pip_flexion": 130.0})


# ----------------------------------------------------------------------------- S01 round trip

@pytest.mark.parametrize("grasp", GRASPS)
def test_s01_glove_angles_recover_truth(grasp):
    res = kin.grasp_angles(S01, grasp)
    assert len(res.trials) == 6
    assert set(res.measured) == set(kin.joint_table()) - UNMEASURED
    truths = [_truth(S01 / "glove" / f"{grasp}_{t:02d}.truth.csv") for t, _, _ in res.trials]
    for (_, _, ang), truth in zip(res.trials, truths, strict=True):
        for dof, v in truth.items():
            assert ang[dof] == pytest.approx(v, abs=0.3), dof
    pose = kin.grasp_pose(S01, grasp)
    assert isinstance(pose, kin.Pose)
    for dof in res.measured:
        assert pose[dof] == pytest.approx(np.mean([t[dof] for t in truths]), abs=0.15), dof
    for dof in UNMEASURED:
        assert pose[dof] == kin.joint_table()[dof].neutral
    ms = res.mean_sd()
    assert 0.3 < ms["index_pip_flexion"][1] < 6.0  # trial-to-trial spread (about 2 deg)


def test_grasps_differ_as_expected():
    cyl, sph, pre = (kin.grasp_pose(S01, g) for g in GRASPS)
    assert sph["little_mcp_abduction"] > cyl["little_mcp_abduction"] + 5  # ball: fingers spread
    assert cyl["index_mcp_flexion"] > sph["index_mcp_flexion"] + 5  # power grasp wraps
    assert pre["ring_pip_flexion"] > pre["index_pip_flexion"] + 10  # tucked ulnar fingers


def test_hold_detected_from_emg_when_trials_toml_has_none(tmp_path):
    trials = []
    for k in (1, 2):
        trials.append(f'  {{ trial = {k}, emg = "{S01}/emg/spherical_0{k}.csv.gz", '
                      f'glove = "{S01}/glove/spherical_0{k}.csv.gz" }},')
    (tmp_path / "trials.toml").write_text(
        f'[emg]\nmains_hz = 50.0\n[glove]\nformat = "raw"\n'
        f'calibration = "{S01}/glove/calibration.csv"\n'
        "[grasps.spherical]\ntrials = [\n" + "\n".join(trials) + "\n]\n")
    res = kin.grasp_angles(tmp_path, "spherical")
    ref = kin.grasp_angles(S01, "spherical", trial=1)
    (_, hold, ang), (_, hold_ref, ang_ref) = res.trials[0], ref.trials[0]
    assert hold[0] == pytest.approx(hold_ref[0], abs=0.1)
    assert ang["index_mcp_flexion"] == pytest.approx(ang_ref["index_mcp_flexion"], abs=0.3)


# ----------------------------------------------------------------------------- calibration

def _write(path: Path, header: list[str], rows: list[list[float]]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(",".join(header) + "\n"
                    + "\n".join(",".join(f"{v:g}" for v in r) for r in rows) + "\n")


def test_cross_coupled_linear_calibration(tmp_path):
    cal = tmp_path / "cal.csv"
    cal.write_text("# test\ndof,sensor,gain\nring_mcp_abduction,mr,0.5\nring_mcp_abduction,"
                   "offset,-10\nlittle_mcp_abduction,rl,0.4\nlittle_mcp_abduction,mr,0.5\n"
                   "little_mcp_abduction,offset,-30\n")
    c = kin.read_glove_calibration(cal)
    assert c.sensors == ("mr", "rl")
    out = c.apply({"mr": np.array([30.0]), "rl": np.array([100.0])})
    assert out["ring_mcp_abduction"][0] == pytest.approx(5.0)
    assert out["little_mcp_abduction"][0] == pytest.approx(0.4 * 100 + 0.5 * 30 - 30)
    with pytest.raises(InputError, match="sensor 'rl' .* missing"):
        c.apply({"mr": np.array([1.0])}, "glove.csv")
    cal.write_text("dof,sensor,gain\nindex_knuckle,s1,0.5\n")
    with pytest.raises(InputError, match="unknown joint DOF 'index_knuckle'"):
        kin.read_glove_calibration(cal)


def _glove_subject(root: Path, fmt: str, header: list[str], rows: list[list[float]],
                   calibration: str = "") -> Path:
    _write(root / "glove" / "g1.csv", ["time_s", *header], rows)
    cal = f'calibration = "{calibration}"\n' if calibration else ""
    (root / "trials.toml").write_text(
        f'[glove]\nformat = "{fmt}"\n{cal}[grasps.test]\n'
        'trials = [ { trial = 1, glove = "glove/g1.csv", hold_s = [0.02, 0.08] } ]\n')
    return root


def test_angles_format_and_limits_error(tmp_path):
    rows = [[0.01 * i, 30.0, 5.0] for i in range(10)]
    _glove_subject(tmp_path, "angles", ["index_pip_flexion", "index_mcp_abduction"], rows)
    pose = kin.grasp_pose(tmp_path, "test")
    assert pose["index_pip_flexion"] == pytest.approx(30.0)
    rows[6][1] = 118.0  # beyond the 110 deg PIP limit, at t = 0.06 s
    _glove_subject(tmp_path, "angles", ["index_pip_flexion", "index_mcp_abduction"], rows)
    with pytest.raises(InputError, match=r"g1.csv: index_pip_flexion = 118.0 deg at "
                                         r"t = 0.060 s is outside the joint limits \[0, 110\]"):
        kin.grasp_pose(tmp_path, "test")


def test_raw_calibration_out_of_limits_and_bad_columns(tmp_path):
    cal = tmp_path / "cal.csv"
    cal.write_text("dof,sensor,gain\nwrist_deviation,yaw,1.0\nwrist_deviation,offset,-50\n")
    rows = [[0.01 * i, 60.0] for i in range(10)]
    _glove_subject(tmp_path, "raw", ["yaw"], rows, calibration=str(cal))
    assert kin.grasp_pose(tmp_path, "test")["wrist_deviation"] == pytest.approx(10.0)
    rows[0][1] = 10.0  # -40 deg deviation: below -20, at t = 0 (outside the hold, still wrong)
    _glove_subject(tmp_path, "raw", ["yaw"], rows, calibration=str(cal))
    with pytest.raises(InputError, match=r"wrist_deviation = -40.0 deg at t = 0.000 s"):
        kin.grasp_pose(tmp_path, "test")
    _glove_subject(tmp_path, "raw", ["pitch"], rows, calibration=str(cal))
    with pytest.raises(InputError, match="sensor 'yaw' .* missing"):
        kin.grasp_pose(tmp_path, "test")
    _glove_subject(tmp_path, "angles", ["index_bend"], rows)
    with pytest.raises(InputError, match="column 'index_bend' is not a joint DOF"):
        kin.grasp_pose(tmp_path, "test")


# ----------------------------------------------------------------------------- CLI

def test_cli_angles(tmp_path, capsys):
    rc = main(["angles", "--subject", str(S01), "--grasp", "cylindrical", "--out", str(tmp_path)])
    assert rc == 0
    out = capsys.readouterr().out
    assert "index_mcp_flexion" in out and "SYNTHETIC" in out
    pose = kin.Pose.from_toml(tmp_path / "pose.toml")
    assert pose["index_mcp_flexion"] == pytest.approx(55.0, abs=0.3)
    with (tmp_path / "joint_angles.csv").open() as fh:
        rows = list(csv.DictReader(ln for ln in fh if not ln.startswith("#")))
    assert len(rows) == 27
    rc = main(["angles", "--subject", str(S01), "--grasp", "lateral", "--out", str(tmp_path)])
    assert rc == 2 and "no grasp 'lateral'" in capsys.readouterr().err
