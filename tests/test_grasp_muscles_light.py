"""The muscle-driven mode end to end on the real finite-element hand, in CI (issue 6), 2 ranks.

The shipped muscle-driven recipe (``workflows/cylindrical_muscles.toml``: closing to 1 N per
digit, then the EMG muscle torques balanced against ligaments and contact with the flexion
DOFs released, then the Uzawa phase to the 0.01 mm target) on the cylinder with thumb and
index taking part (middle, ring and little not meshed) and every muscle force at 0.1 of the
subject's EMG estimate (``muscle_force_scale = 0.1``): 5 released joints, 15.1k dofs, ~75 s
per run on 2 ranks. The whole-hand runs at full load take 15-45 min (docs/grasp.md) and are
not CI material; the other muscle-mode tests drive the same code with stand-in FE problems
(tests/test_grasp_config.py), this one with the real one.

Measured (7 Dec 2026, thirty-ninth session, ``mpirun -n 2 --allow-run-as-root
.venv/bin/python scripts/mpi-pytest.py -q -m mpi tests/test_grasp_muscles_light.py``): done
in 75 s, 308 Newton iterations, torque residual <= 1.6e-4 of the applied torque at every
released joint, penetration 0.0059 mm, object force = reactions to 9e-15; thumb 5.12 N, index
1.505 N. FDP + 10 %: index 1.566 N (+4 %), thumb unchanged.
"""

import os
from dataclasses import replace

import numpy as np
import pytest
from mpi4py import MPI
from test_grasp_power_light import _two_digit_grasp  # pytest puts tests/ on sys.path
from test_grasp_run import decisions, first_difference, run_on_rank0_too

from handfe.emg import muscle_forces
from handfe.grasp import run_workflow
from handfe.grasp.config import load_workflow

COMM = MPI.COMM_WORLD
DIGITS = ("thumb", "index")
#: workflow muscle_force_scale: every muscle at 0.1 of its EMG force (the full load takes the
#: whole hand 15-45 min)
LOAD = 0.1
pytestmark = [pytest.mark.mpi, pytest.mark.slow,
              pytest.mark.skipif(COMM.size == 1,
                                 reason="2-rank regression; runs under make test-mpi")]


def _run(folder, name: str, fdp: float = 1.0):
    wf = load_workflow("cylindrical_muscles")
    assert wf.loading == "muscles"
    wf = replace(wf, grasp=str(folder / "cylindrical_ci.toml"), mesh="coarse",
                 muscle_force_scale=LOAD, outputs=replace(wf.outputs, fields=False))
    scale = {"FDP": fdp} if fdp != 1.0 else None
    return wf, run_workflow(wf, out_dir=folder / name, muscle_scale=scale, progress=False)


@pytest.fixture(scope="module")
def light_muscles(tmp_path_factory):
    """The light muscle-driven cylinder (thumb + index), run once for the tests below:
    (workflow, result, folder)."""
    folder = tmp_path_factory.mktemp("cylinder_muscles") if COMM.rank == 0 else None
    if COMM.rank == 0:
        _two_digit_grasp("cylindrical", folder)
    folder = COMM.bcast(folder, root=0)
    wf, res = _run(folder, "base")
    return wf, res, folder


def test_muscle_driven_grasp_balances_every_released_joint(light_muscles):
    """The run ends done; at every released joint muscle + ligament + tissue/contact torques
    balance to torque_rtol (1e-3) of the joint's largest term; the equilibrium angles are
    reported next to the measured ones; the object's force equals the reactions (1e-6); the
    pads meet the 0.01 mm penetration target; only thumb and index touch the object."""
    wf, res, folder = light_muscles
    COMM.barrier()
    s = res.summary
    assert s["status"] == "done", s.get("error")
    assert s["loading"] == "muscles"
    emg = {m: f for m, (f, _sd) in muscle_forces(wf.subject_dir(), "cylindrical").items()}
    for m, f in emg.items():  # muscle_force_scale scales every muscle
        assert s["muscle_forces_N"][m] == pytest.approx(LOAD * f, rel=1e-12), m
    assert s["muscle_force_scale"] == LOAD and s["settings"]["muscle_force_scale"] == LOAD
    assert set(s["skipped"]["digits"]) == {"middle", "ring", "little"}
    joints = s["joints"]
    assert {j.split("_")[0] for j in joints} == set(DIGITS)
    assert len(joints) == 5  # thumb CMC, MCP; index MCP, PIP, DIP (flexion)
    for name, j in joints.items():
        assert not j["at_limit"] and j["relative_residual"] <= wf.solver.torque_rtol, (name, j)
        total = j["muscle_Nmm"] + j["ligament_Nmm"] + j["tissue_contact_Nmm"] + j["coupling_Nmm"]
        assert total == pytest.approx(j["residual_Nmm"], abs=1e-9 * abs(j["muscle_Nmm"])), name
        assert np.isfinite([j["measured_deg"], j["equilibrium_deg"]]).all(), name
    # the muscles moved the digits off the kinematic closing: a balance, not a posture
    assert max(abs(j["equilibrium_deg"] - j["start_deg"]) for j in joints.values()) > 0.1
    assert s["max_relative_torque_residual"] <= wf.solver.torque_rtol
    assert s["equilibrium_relative_error"] < 1e-6
    assert s["max_penetration_mm"] <= wf.solver.penetration_tol_mm
    for d in DIGITS:
        assert res.regions[d]["normal_force_N"] > 0.5, (d, res.regions[d])
    for r in ("middle", "ring", "little", "palm"):
        assert res.regions[r]["normal_force_N"] == 0.0, r
    if COMM.rank == 0:
        for f in ("regions.csv", "fingertips.csv", "summary.json", "pressure.png"):
            assert (folder / "base" / f).is_file(), f


def test_more_flexor_force_never_lowers_the_contact_force_of_its_digit(light_muscles):
    """FDP (the index's deep flexor) 10 % stronger, every other muscle as before, on the same
    mesh (the mesh cache): the index presses the object at least as hard (measured +4 %), and
    the thumb, which FDP does not cross, within 1 % of before."""
    _, base, folder = light_muscles
    _, more = _run(folder, "fdp_plus_10", fdp=1.1)
    assert more.summary["status"] == "done", more.summary.get("error")
    assert more.summary["dofs"] == base.summary["dofs"]
    f0, f1 = base.regions["index"]["normal_force_N"], more.regions["index"]["normal_force_N"]
    assert f1 >= f0, (f0, f1)
    assert more.regions["thumb"]["normal_force_N"] == pytest.approx(
        base.regions["thumb"]["normal_force_N"], rel=1e-2)


@pytest.mark.skipif(COMM.size != 2, reason="1- vs 2-rank comparison; runs under make test-mpi")
@pytest.mark.skipif(os.environ.get("HANDFE_GRASP_E2E") != "1",
                    reason="opt-in (HANDFE_GRASP_E2E=1): +120 s; the pinch's 1- vs 2-rank test "
                    "runs in CI (tests/test_grasp_run.py)")
def test_muscle_driven_grasp_one_rank_matches_two_ranks(light_muscles):
    """The same run on rank 0 alone, on the same mesh (the mesh cache): the same path (load
    steps, Newton iterations, Uzawa updates) and the same equilibrium angles and forces.
    Measured 7 Dec 2026: 308 iterations on both, grip 6.624721525938 N on both (to 1e-14),
    angles to 1e-12 deg; 120 s on 1 rank, 75 s on 2. Round-off can flip a decision of a
    frictional, load-stepped path (the parallel LU is not bit-reproducible: docs/grasp.md; the
    light ball's two 2-rank runs parted at a closing Uzawa update, 16.3 vs 15.8 N of grip):
    then both runs must still be balanced, and the test is marked xfail, naming the decision
    (as the pinch's, tests/test_grasp_run.py)."""
    wf, res2, _ = light_muscles
    (s1, reg1), (s2, reg2) = run_on_rank0_too(wf, res2)
    diff = first_difference(decisions(s1), decisions(s2))
    if diff is not None:
        for s in (s1, s2):
            assert s["max_relative_torque_residual"] <= wf.solver.torque_rtol
            assert s["equilibrium_relative_error"] < 1e-6
            assert s["max_penetration_mm"] <= wf.solver.penetration_tol_mm
        pytest.xfail(f"1 and 2 ranks took different decisions ({diff[1]}; 1 rank first): grip "
                     f"{s1['grip_force_N']:.4f} vs {s2['grip_force_N']:.4f} N")
    assert s1["grip_force_N"] == pytest.approx(s2["grip_force_N"], rel=1e-6)
    for j in s2["joints"]:
        assert s1["joints"][j]["equilibrium_deg"] == pytest.approx(
            s2["joints"][j]["equilibrium_deg"], abs=1e-6), j
    for k in reg2:
        assert reg1[k]["normal_force_N"] == pytest.approx(reg2[k]["normal_force_N"], rel=1e-5,
                                                          abs=1e-8), k
