"""Sensitivity driver (issue 7): material refit, study files, MPI groups, case files, resume,
failure handling, tables. The FE end-to-end study uses the layered fingertip on the coarse mesh
(no grasp code). Tests marked mpi also run under `mpirun -n 2` (two groups of one rank); case
folders are shared between ranks (rank 0's tmp_path)."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
from mpi4py import MPI

from handfe.cli import main
from handfe.errors import ConfigError
from handfe.materials import Ogden
from handfe.sensitivity import (
    build_tables,
    load_study,
    refit_scaled,
    run_study,
    study_cases,
    study_from_dict,
    uniaxial_nominal_stress,
)

COMM = MPI.COMM_WORLD
REPO = Path(__file__).resolve().parent.parent
DENSE = np.linspace(0.6, 1.5, 301)


def shared_dir(tmp_path: Path) -> Path:
    """The same folder on every rank (rank 0's tmp_path)."""
    return Path(COMM.bcast(str(tmp_path) if COMM.rank == 0 else None, root=0))


def curve_error_pct(mu, alpha, target) -> float:
    """max |P - P_target| / max(|P_target|, 5 % of its peak) over DENSE, in %."""
    P = uniaxial_nominal_stress(mu, alpha, DENSE)
    w = np.maximum(np.abs(target), 0.05 * np.max(np.abs(target)))
    return float(np.max(np.abs(P - target) / w) * 100.0)


# --------------------------------------------------------------------------------------------
# Material refit
# --------------------------------------------------------------------------------------------
@pytest.mark.parametrize("tissue", ["skin", "subcutaneous"])
def test_refit_of_unscaled_data_reproduces_baseline(tissue):
    base = getattr(Ogden, tissue)()
    r = refit_scaled(base, 0.0, tissue=tissue)
    target = uniaxial_nominal_stress(base.mu_MPa, base.alpha, DENSE)
    assert curve_error_pct(r.mu_MPa, r.alpha, target) < 0.5
    assert r.fit_max_pct < 0.5 and r.stable and r.ok
    assert sum(r.mu_MPa) == pytest.approx(sum(base.mu_MPa), rel=5e-3)


@pytest.mark.parametrize("tissue,delta", [("skin", 0.10), ("skin", -0.20),
                                          ("subcutaneous", 0.05)])
def test_refit_of_scaled_data_reproduces_scaled_curve(tissue, delta):
    base = getattr(Ogden, tissue)()
    r = refit_scaled(base, delta, tissue=tissue)
    target = (1 + delta) * uniaxial_nominal_stress(base.mu_MPa, base.alpha, DENSE)
    assert curve_error_pct(r.mu_MPa, r.alpha, target) < 1.0
    assert r.ok and r.stable and not r.poor
    # the initial shear modulus scales with the curve; the individual mu_i need not
    assert sum(r.mu_MPa) == pytest.approx((1 + delta) * sum(base.mu_MPa), rel=0.01)
    assert np.isfinite(r.mu_vs_scaled_pct) and r.alpha_change_pct < 5.0
    d = r.to_dict()
    assert d["ok"] and len(d["mu_MPa"]) == 3 and json.dumps(d)


def test_refit_poor_fit_is_flagged():
    r = refit_scaled(Ogden.skin(), 0.1, tissue="skin", max_fit_error_pct=1e-12)
    assert r.poor and not r.ok and "poor fit" in r.problem


# --------------------------------------------------------------------------------------------
# Study files
# --------------------------------------------------------------------------------------------
FT = {"name": "t", "kind": "fingertip", "parameters": ["skin", "force"], "levels_pct": [-10, 10],
      "fingertip": {"mesh": "coarse", "force_N": 1.0}}


def test_shipped_fingertip_study_loads():
    st = load_study(REPO / "sensitivity" / "fingertip_small.toml")
    assert st.kind == "fingertip" and st.regions == ("pad",)
    assert [c.id for c in study_cases(st)][:3] == ["baseline", "skin_m20", "skin_m10"]


@pytest.mark.parametrize("name", ["cylindrical", "precision_small", "cylindrical_fdp"])
def test_shipped_grasp_studies(name):
    """The shipped grasp studies load; the muscle-force ones run the muscle-driven recipe."""
    st = load_study(REPO / "sensitivity" / f"{name}.toml")
    assert st.kind == "grasp"
    muscles = [p for p in st.parameters if p not in ("skin", "subcutaneous")]
    if muscles:
        assert st.baseline_loading() == "muscles", name
        assert st.workflow_path().name == "cylindrical_muscles.toml", name


def test_muscle_parameters_need_muscle_loading():
    """workflows/precision.toml closes the digits by angles, where the muscle forces do not
    act: a muscle parameter would tabulate zero changes, so the study is refused, naming the
    file, the parameter and the workflow; loading = "muscles" (or materials only) is fine."""
    base = {"name": "g", "kind": "grasp", "workflow": "workflows/precision.toml",
            "levels_pct": [10]}
    src = str(REPO / "sensitivity" / "g.toml")
    with pytest.raises(ConfigError) as ei:
        study_from_dict({**base, "parameters": ["skin", "FDP"]}, source=src)
    msg = str(ei.value)
    assert "g.toml" in msg and "'parameters[1]' = 'FDP'" in msg and "precision.toml" in msg
    with pytest.raises(ConfigError, match="'loading' = 'angles'"):
        study_from_dict({**base, "parameters": ["FDS"], "loading": "angles"}, source=src)
    assert study_from_dict({**base, "parameters": ["skin", "FDP"], "loading": "muscles"},
                           source=src).baseline_loading() == "muscles"
    assert study_from_dict({**base, "parameters": ["skin"]}, source=src
                           ).baseline_loading() == "angles"
    with pytest.raises(ConfigError, match="'loading' = 'muscles': only for kind = 'grasp'"):
        study_from_dict({**FT, "loading": "muscles"}, source=src)


@pytest.mark.parametrize("change,needle", [
    ({"colour": 1}, "unknown key 'colour'"),
    ({"parameters": ["skin", "FDS"]}, "'parameters[1]' = 'FDS'"),
    ({"parameters": []}, "'parameters' is empty"),
    ({"levels_pct": [0, 10]}, "level 0 %"),
    ({"levels_pct": [10, 10]}, "duplicate"),
    ({"levels_pct": "ten"}, "'levels_pct'"),
    ({"kind": "glove"}, "'kind' = 'glove'"),
    ({"metrics": ["normal_force_N"]}, "'metrics[0]' = 'normal_force_N'"),
    ({"regions": ["thumb"]}, "'pad'"),
    ({"refit": {"policy": "ignore"}}, "'refit.policy' = 'ignore'"),
    ({"refit": {"fit_stretch": [1.5, 0.6]}}, "need lo < hi"),
    ({"fingertip": {"force_N": -1.0}}, "'fingertip.force_N'"),
    ({"levels_by_parameter": {"FDS": [5]}}, "'levels_by_parameter.FDS'"),
    ({"kind": "grasp", "parameters": ["FDS"], "metrics": [], "fingertip": {}},
     "missing 'workflow'"),
    ({"kind": "grasp", "parameters": ["XYZ"], "workflow": "nowhere.toml", "fingertip": {}},
     "'parameters[0]' = 'XYZ'"),
])
def test_bad_study_rejected(change, needle):
    with pytest.raises(ConfigError, match=None) as ei:
        study_from_dict({**FT, **change}, source="bad.toml")
    assert needle in str(ei.value) and "bad.toml" in str(ei.value)


def test_bad_study_files_and_cli_exit_code(tmp_path, capsys):
    p = tmp_path / "s.toml"
    p.write_text('name = "x"\nkind = "fingertip"\nparameters = ["skin"\n')
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_study(p)
    with pytest.raises(ConfigError, match="file not found"):
        load_study(tmp_path / "missing.toml")
    p.write_text('name = "x"\nkind = "fingertip"\nparameters = ["skin", "FDP"]\n')
    assert main(["sensitivity", str(p), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "s.toml" in err and "'parameters[1]' = 'FDP'" in err and "Traceback" not in err


# --------------------------------------------------------------------------------------------
# Driver with a cheap analytic runner (no FE): failures, skips, resume after a kill
# --------------------------------------------------------------------------------------------
def fake_runner(study, spec, comm):
    """Deterministic stand-in for the fingertip scene: softer skin / more force -> larger
    area and deflection."""
    s = sum(spec.materials["skin"].mu_MPa) / sum(Ogden.skin().mu_MPa)
    f = spec.load_scale
    return {"regions": {"pad": {"contact_area_mm2": 100.0 * f**0.6 * s**-0.3,
                                "mean_pressure_kPa": 10.0 * f**0.4 * s**0.3,
                                "peak_pressure_kPa": 25.0 * f**0.5 * s**0.3,
                                "deflection_mm": 2.0 * f**0.5 * s**-0.5}}, "info": {}}


def read_tables(out: Path) -> dict[str, str]:
    """The result CSVs (status.csv, with wall times and finish times, is a log, not a result)."""
    return {p.name: p.read_text() for p in sorted(out.glob("*.csv")) if p.name != "status.csv"}


@pytest.mark.mpi
def test_failing_case_is_recorded_and_the_rest_go_on(tmp_path):
    out = shared_dir(tmp_path)
    st = study_from_dict(FT, source="ft.toml")

    def runner(study, spec, comm):
        if spec.case.id == "force_p10":
            raise RuntimeError("injected failure")
        return fake_runner(study, spec, comm)

    res = run_study(st, out, runner=runner, progress=False, charts=False)
    assert res.statuses["force_p10"] == "failed"
    assert all(s == "ok" for k, s in res.statuses.items() if k != "force_p10")
    rec = json.loads((out / "cases" / "force_p10.json").read_text())
    assert "injected failure" in rec["error"] and rec["status"] == "failed"
    if COMM.rank == 0:
        rows = list(csv.DictReader((out / "status.csv").open()))
        bad = [r for r in rows if r["case_id"] == "force_p10"][0]
        assert "injected failure" in bad["error"]
        tab = list(csv.DictReader((out / "table_force.csv").open()))
        assert tab[0]["+10%"] == "" and tab[0]["-10%"] != ""
    COMM.barrier()
    # a re-run retries only the failed case
    calls = []

    def counting(study, spec, comm):
        calls.append(spec.case.id)
        return fake_runner(study, spec, comm)

    res2 = run_study(st, out, runner=counting, progress=False, charts=False)
    assert COMM.allreduce(len(calls)) == 1 and all(s == "ok" for s in res2.statuses.values())
    # --force re-runs everything
    calls.clear()
    run_study(st, out, runner=counting, force=True, progress=False, charts=False)
    assert COMM.allreduce(len(calls)) == 5


@pytest.mark.mpi
def test_interrupted_study_resumes_to_identical_tables(tmp_path):
    root = shared_dir(tmp_path)
    st = study_from_dict({**FT, "levels_pct": [-20, -10, 10, 20]}, source="ft.toml")
    full, cut = root / "full", root / "cut"
    run_study(st, full, runner=fake_runner, progress=False, charts=False)
    calls = [0]

    def killed(study, spec, comm):
        calls[0] += 1
        if calls[0] == 3:  # every group dies in its third case, like a killed job
            raise KeyboardInterrupt
        return fake_runner(study, spec, comm)

    with pytest.raises(KeyboardInterrupt):
        run_study(st, cut, runner=killed, progress=False, charts=False)
    COMM.barrier()
    n_done = len(list((cut / "cases").glob("*.json")))
    assert n_done == 2 * COMM.size < 9
    res = run_study(st, cut, runner=fake_runner, progress=False, charts=False)
    assert res.reused == n_done and res.ran == 9 - n_done
    if COMM.rank == 0:
        assert read_tables(cut) == read_tables(full)
        assert len(read_tables(full)) == 4  # 2 parameter tables, long, refits
    COMM.barrier()


def test_tables_content_and_cli_tables_only(tmp_path, capsys):
    st = study_from_dict(FT, source="ft.toml")
    out = tmp_path / "o"
    run_study(st, out, runner=fake_runner, progress=False, comm=MPI.COMM_SELF)
    rows = list(csv.DictReader((out / "sensitivity_long.csv").open()))
    assert list(rows[0])[:7] == ["parameter", "level_pct", "region", "metric", "value",
                                 "pct_change", "ratio_of_pct_change"]
    r = next(x for x in rows if x["parameter"] == "force" and x["level_pct"] == "10"
             and x["metric"] == "contact_area_mm2")
    expect = (1.1**0.6 - 1) * 100
    assert float(r["pct_change"]) == pytest.approx(expect, rel=1e-5)
    assert float(r["ratio_of_pct_change"]) == pytest.approx(expect / 10, rel=1e-5)
    tab = list(csv.DictReader((out / "table_skin.csv").open()))
    assert [t["region"] for t in tab] == ["pad"] * 4
    assert list(tab[0]) == ["metric", "region", "unit", "baseline", "-10%", "-10% change",
                            "+10%", "+10% change"]
    refits = list(csv.DictReader((out / "refits.csv").open()))
    assert [x["case_id"] for x in refits] == ["skin_m10", "skin_p10"]
    assert all(x["stable"] == "1" and x["used"] == "1" for x in refits)
    for m in st.metrics:
        assert (out / f"tornado_{m}.png").stat().st_size > 5_000
    before = read_tables(out)
    (out / "table_skin.csv").unlink()
    (out / "sensitivity_long.csv").write_text("garbage")
    toml = tmp_path / "ft.toml"
    toml.write_text('name = "t"\nkind = "fingertip"\nparameters = ["skin", "force"]\n'
                    'levels_pct = [-10, 10]\n[fingertip]\nmesh = "coarse"\nforce_N = 1.0\n')
    assert main(["sensitivity", str(toml), "--out", str(out), "--tables-only"]) == 0
    assert read_tables(out) == before
    build_tables(st, out)
    assert read_tables(out) == before


def test_refit_policy_skip_and_run(tmp_path):
    poor = {**FT, "parameters": ["skin"], "refit": {"max_fit_error_pct": 1e-12}}
    res = run_study(study_from_dict(poor, source="p.toml"), tmp_path / "skip",
                    runner=fake_runner, progress=False, comm=MPI.COMM_SELF, charts=False)
    assert res.statuses == {"baseline": "ok", "skin_m10": "skipped", "skin_p10": "skipped"}
    rec = json.loads((tmp_path / "skip" / "cases" / "skin_p10.json").read_text())
    assert "poor fit" in rec["flag"] and rec["regions"] == {}
    poor["refit"] = {"max_fit_error_pct": 1e-12, "policy": "run"}
    res = run_study(study_from_dict(poor, source="p.toml"), tmp_path / "run",
                    runner=fake_runner, progress=False, comm=MPI.COMM_SELF, charts=False)
    assert set(res.statuses.values()) == {"ok"}
    rows = list(csv.DictReader((tmp_path / "run" / "sensitivity_long.csv").open()))
    assert all("poor fit" in r["flag"] for r in rows if r["parameter"] == "skin")


# --------------------------------------------------------------------------------------------
# End to end with the FE fingertip scene (layered Ogden; P1-P0 on an h = 3 mm mesh, 0.15 N)
# --------------------------------------------------------------------------------------------
FE_STUDY = {"name": "fe", "kind": "fingertip", "parameters": ["skin", "force"],
            "levels_pct": [-10, 10],
            "fingertip": {"force_N": 0.15, "mesh": "reduced", "h_mm": 3.0, "element": "p1-p0",
                          "force_rtol": 0.03}}


@pytest.mark.mpi
@pytest.mark.slow
@pytest.mark.skipif(COMM.size == 1, reason="runs under mpirun -n 2 (make test-mpi): ~3 min, "
                    "not repeated serially")
def test_fingertip_study_end_to_end_and_resume(tmp_path):
    """5 FE cases (on 2 ranks: two groups of one rank); a re-run finds them all on disk, runs
    nothing and rebuilds identical tables. (Resume after a kill / deleted files is tested with
    the analytic runner above: the FE cases would cost ~30 s each here.)"""
    out = shared_dir(tmp_path)
    st = study_from_dict(FE_STUDY, source="fe.toml")
    res = run_study(st, out, progress=False, charts=False)
    assert set(res.statuses.values()) == {"ok"}, res.statuses
    recs = {c.id: json.loads((out / "cases" / f"{c.id}.json").read_text())
            for c in study_cases(st)}
    pad = {k: r["regions"]["pad"] for k, r in recs.items()}
    for k, p in pad.items():
        target = 0.15 * recs[k]["inputs"]["load_scale"]
        assert p["force_N"] == pytest.approx(target, rel=0.03)
        assert p["contact_area_mm2"] > 0 and p["peak_pressure_kPa"] >= p["mean_pressure_kPa"] > 0
        assert p["max_penetration_mm"] <= 0.01 + 1e-9
    # more plate force: deeper and wider; stiffer skin (+10 % stress): less deflection
    assert pad["force_p10"]["deflection_mm"] > pad["baseline"]["deflection_mm"] > \
        pad["force_m10"]["deflection_mm"]
    assert pad["skin_p10"]["deflection_mm"] < pad["skin_m10"]["deflection_mm"]
    assert recs["skin_p10"]["refit"]["stable"] and recs["skin_p10"]["refit"]["fit_max_pct"] < 1
    before = read_tables(out) if COMM.rank == 0 else None
    COMM.barrier()
    if COMM.rank == 0:
        (out / "table_skin.csv").unlink()
    COMM.barrier()
    res2 = run_study(st, out, progress=False, charts=False)
    assert res2.ran == 0 and res2.reused == 5
    if COMM.rank == 0:
        assert read_tables(out) == before
    COMM.barrier()


def test_grasp_runner_plumbing(tmp_path, monkeypatch):
    """The grasp case runner against handfe.grasp's API, with run_workflow replaced by a stub
    (the real grasp solve is far too slow for a unit test)."""
    from types import SimpleNamespace

    import handfe.grasp.scene as scene

    calls = []

    def stub(wf, *, mesh=None, out_dir=None, comm=None, materials=None, muscle_scale=None,
             loading=None, progress=True):
        calls.append(dict(wf=wf, mesh=mesh, materials=materials, muscle_scale=muscle_scale,
                          loading=loading))
        progress("mesh (coarse): 1 tets")  # the case's progress goes to its log file
        f = (muscle_scale or {}).get("FDP", 1.0)
        regions = {r: {"contact_area_mm2": 50.0 * f, "mean_pressure_kPa": 30.0,
                       "peak_pressure_kPa": 90.0, "normal_force_N": 1.5 * f,
                       "tangential_force_N": 0.2} for r in ("thumb", "index", "middle", "palm")}
        return SimpleNamespace(regions=regions, summary={"status": "done", "path": tmp_path})

    monkeypatch.setattr(scene, "run_workflow", stub)
    st = study_from_dict({"name": "g", "kind": "grasp", "workflow": "workflows/precision.toml",
                          "loading": "muscles", "parameters": ["skin", "FDP"],
                          "levels_pct": [10],
                          "regions": ["thumb", "index", "middle"]},
                         source=str(REPO / "sensitivity" / "g.toml")).with_mesh("coarse")
    res = run_study(st, tmp_path, progress=False, charts=False, comm=MPI.COMM_SELF)
    assert set(res.statuses.values()) == {"ok"}
    by_case = {("FDP" if c["muscle_scale"] else "skin" if c["materials"]["skin"].mu_MPa !=
                Ogden.skin().mu_MPa else "baseline"): c for c in calls}
    assert set(by_case) == {"baseline", "skin", "FDP"}
    assert all(c["mesh"] == "coarse" and c["loading"] == "muscles" for c in calls)
    assert by_case["FDP"]["muscle_scale"] == {"FDP": pytest.approx(1.1)}
    nu = calls[0]["wf"].solver.nu
    assert all(m.nu == nu for c in calls for m in c["materials"].values())
    rows = list(csv.DictReader((tmp_path / "table_FDP.csv").open()))
    r = next(x for x in rows if x["metric"] == "normal_force_N" and x["region"] == "index")
    assert float(r["+10% change"]) == pytest.approx(10.0, rel=1e-4)
    # each case's progress lines in OUT/cases/<case-id>.log, with the case's elapsed time
    for cid in ("baseline", "FDP_p10", "skin_p10"):
        text = (tmp_path / "cases" / f"{cid}.log").read_text()
        assert text.endswith("s] mesh (coarse): 1 tets\n") and text.startswith("["), text
