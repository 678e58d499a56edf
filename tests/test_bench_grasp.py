"""benchmarks/grasp_time_vs_error.py on finished run folders (``--from-runs``): the error
arithmetic of the README's grasp table, without a solve."""

from __future__ import annotations

import csv
import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "benchmarks" / "grasp_time_vs_error.py"
DIGITS = ("thumb", "index", "middle", "ring", "little")


def _run_folder(d: Path, *, area: dict[str, float], pad_kpa: dict[str, float],
                pad_force_N: dict[str, float], wall_s: float, status: str = "done",
                pad_peak_kpa: dict[str, float] | None = None) -> Path:
    """A stand-in ``handfe run`` folder: summary.json, regions.csv, fingertips.csv."""
    d.mkdir(parents=True)
    (d / "summary.json").write_text(json.dumps({
        "status": status, "wall_s": wall_s, "mesh_cells": 1000, "dofs": 900,
        "newton_iterations": 10, "grip_force_N": 15.0, "peak_memory_GB_per_rank": 1.5}))
    cols = ("contact_area_mm2", "mean_pressure_kPa", "peak_pressure_kPa", "normal_force_N",
            "tangential_force_N")
    with (d / "regions.csv").open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(("region", *cols))
        for r in (*DIGITS, "palm"):
            w.writerow((r, area.get(r, 0.0), 10.0, 20.0, pad_force_N.get(r, 0.0), 0.0))
            if r != "palm":
                w.writerow((f"{r}_distal", area.get(r, 0.0), pad_kpa.get(r, 0.0), 1.0,
                            pad_force_N.get(r, 0.0), 0.0))
    with (d / "fingertips.csv").open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(("digit", "mean_pressure_kPa", "peak_pressure_kPa", "contact_area_mm2"))
        for r in DIGITS:
            w.writerow((r, pad_kpa.get(r, 0.0), (pad_peak_kpa or {}).get(r, 1.0),
                        area.get(r, 0.0)))
    return d


def _bench(tmp_path: Path, runs: dict[str, Path]) -> subprocess.CompletedProcess:
    spec = ",".join(f"precision:{lv}={d}" for lv, d in runs.items())
    return subprocess.run([sys.executable, str(SCRIPT), "--grasps", "precision", "--levels",
                           ",".join(runs), "--from-runs", spec, "--out", str(tmp_path / "out")],
                          capture_output=True, text=True, cwd=ROOT, timeout=300)


def test_errors_are_relative_to_the_last_level_and_skip_lightly_loaded_pads(tmp_path):
    ref = _run_folder(tmp_path / "fine", area={"thumb": 100.0, "index": 50.0, "middle": 80.0},
                      pad_kpa={"thumb": 40.0, "index": 100.0, "middle": 60.0},
                      pad_force_N={"thumb": 5.0, "index": 5.0, "middle": 0.2}, wall_s=400.0,
                      pad_peak_kpa={"thumb": 100.0, "index": 500.0, "middle": 100.0})
    # thumb area -20 %, index +10 %; index pad pressure +30 %; the middle pad is 3x off but
    # carries 0.2 N (< 0.5 N) in the reference, so it is not compared. The thumb carries
    # 0.8^1.5 of the reference's force, so scaled by a ~ F^(2/3) its area is exact and the
    # index is the worst force-scaled region
    coarse = _run_folder(tmp_path / "coarse",
                         area={"thumb": 80.0, "index": 55.0, "middle": 80.0},
                         pad_kpa={"thumb": 40.0, "index": 130.0, "middle": 180.0},
                         pad_force_N={"thumb": 5.0 * 0.8 ** 1.5, "index": 5.0, "middle": 0.2},
                         wall_s=100.0,
                         pad_peak_kpa={"thumb": 140.0, "index": 400.0, "middle": 900.0})
    p = _bench(tmp_path, {"coarse": coarse, "fine": ref})
    assert p.returncode == 0, p.stderr
    with (tmp_path / "out" / "grasp_time_vs_error.csv").open() as fh:
        rows = {r["level"]: r for r in csv.DictReader(fh)}
    c, f = rows["coarse"], rows["fine"]
    assert float(c["max_rel_err_region_area"]) == pytest.approx(0.2)
    assert c["worst_region"] == "thumb"
    assert float(c["max_rel_err_fingertip_pressure"]) == pytest.approx(0.3)
    assert c["worst_pad"] == "index"
    # peaks: thumb +40 %, index -20 %; the unloaded middle pad's 9x is not compared
    assert float(c["max_rel_err_fingertip_peak_pressure"]) == pytest.approx(0.4)
    assert c["worst_pad_peak"] == "thumb"
    # the forces compared at: the thumb carries 0.8^1.5 of the reference's; the middle's
    # 0.2 N is below the 0.5 N floor
    assert float(c["max_rel_diff_region_force"]) == pytest.approx(1.0 - 0.8 ** 1.5)
    assert c["worst_region_force"] == "thumb"
    assert float(f["max_rel_diff_region_force"]) == 0.0 and f["worst_region_force"] == ""
    assert float(c["max_rel_err_region_area_force_scaled"]) == pytest.approx(0.1)
    assert c["worst_region_force_scaled"] == "index"
    assert float(c["wall_s"]) == 100.0 and c["reference_level"] == "fine"
    assert float(c["peak_memory_GB_per_rank"]) == 1.5  # from summary.json
    assert float(f["max_rel_err_region_area"]) == 0.0 == float(f["max_rel_err_fingertip_pressure"])
    assert (tmp_path / "out" / "grasp_time_vs_error.png").stat().st_size > 0
    with (tmp_path / "out" / "grasp_regions_by_level.csv").open() as fh:
        assert sum(1 for _ in csv.DictReader(fh)) == 2 * 6  # six regions per level


def test_a_partial_run_is_refused_by_name(tmp_path):
    kw = dict(area={"thumb": 1.0}, pad_kpa={"thumb": 1.0}, pad_force_N={"thumb": 1.0})
    ref = _run_folder(tmp_path / "fine", wall_s=1.0, **kw)
    part = _run_folder(tmp_path / "coarse", wall_s=1.0, status="partial", **kw)
    p = _bench(tmp_path, {"coarse": part, "fine": ref})
    assert p.returncode != 0
    assert "coarse" in p.stderr and "'partial'" in p.stderr and "Traceback" not in p.stderr


def test_loaded_area_of_an_older_folder_comes_from_its_pressure_facets(tmp_path):
    """Folders written before regions.csv had ``loaded_area_mm2``: the benchmark takes it from
    pressure_facets.npz (a third of a facet per vertex at >= 10 kPa)."""
    import numpy as np

    tri = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])  # 0.5 mm2
    thumb_distal = 113  # SKIN_OUTER_GMSH + 10 x region 1 + phalanx 3
    folders = {}
    for lv, p in (("coarse", [20.0, 20.0, 9.0]), ("fine", [20.0, 20.0, 20.0])):
        d = _run_folder(tmp_path / lv, area={"thumb": 1.5}, pad_kpa={"thumb": 20.0},
                        pad_force_N={"thumb": 1.0}, wall_s=1.0)
        np.savez(d / "pressure_facets.npz", xf=np.stack([tri] * 3), p_kPa=np.array([p] * 3),
                 codes=np.full(3, thumb_distal), hand_R=np.eye(3), title="t")
        folders[lv] = d
    p = _bench(tmp_path, folders)
    assert p.returncode == 0, p.stderr
    with (tmp_path / "out" / "grasp_time_vs_error.csv").open() as fh:
        rows = {r["level"]: r for r in csv.DictReader(fh)}
    # coarse: two of three vertices loaded per facet -> 1.0 mm2 against 1.5
    assert float(rows["coarse"]["max_rel_err_loaded_area"]) == pytest.approx(1 / 3)
    assert rows["coarse"]["worst_region_loaded"] == "thumb"


def test_an_unreadable_pressure_map_is_named(tmp_path):
    kw = dict(area={"thumb": 1.0}, pad_kpa={"thumb": 1.0}, pad_force_N={"thumb": 1.0})
    ref = _run_folder(tmp_path / "fine", wall_s=1.0, **kw)
    bad = _run_folder(tmp_path / "coarse", wall_s=1.0, **kw)
    (bad / "pressure_facets.npz").write_bytes(b"not a zip")
    p = _bench(tmp_path, {"coarse": bad, "fine": ref})
    assert p.returncode != 0
    assert "pressure_facets.npz" in p.stderr and "Traceback" not in p.stderr


def test_mean_pressure_definitions_from_the_pressure_facets(tmp_path):
    """benchmarks/grasp_mean_pressure_definitions.py: the threshold-based means of a digit
    (area-weighted nodal pressure, and normal force over the loaded area) and their error."""
    import numpy as np

    tri = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])  # 0.5 mm2
    folders = []
    for lv, p in (("coarse", [20.0, 20.0, 9.0]), ("fine", [20.0, 20.0, 20.0])):
        d = _run_folder(tmp_path / lv, area={"thumb": 1.5}, pad_kpa={"thumb": 20.0},
                        pad_force_N={"thumb": 1.0}, wall_s=1.0)
        np.savez(d / "pressure_facets.npz", xf=np.stack([tri] * 3), p_kPa=np.array([p] * 3),
                 codes=np.full(3, 113), hand_R=np.eye(3), title="t")  # thumb distal
        folders.append(str(d))
    script = ROOT / "benchmarks" / "grasp_mean_pressure_definitions.py"
    p = subprocess.run([sys.executable, str(script), "--runs", "pinch=" + ",".join(folders),
                        "--thresholds", "10"], capture_output=True, text=True, cwd=ROOT,
                       timeout=300)
    assert p.returncode == 0, p.stderr
    rows = {r["definition"]: r for r in csv.DictReader(p.stdout.splitlines())}
    assert {r["digit"] for r in rows.values()} == {"thumb"}  # the others carry 0 N
    # loaded area: 1.0 mm2 (coarse: two of three vertices) and 1.5 mm2 (fine), 1 N on both
    assert float(rows["mean_over_10kPa"]["level0_kPa"]) == pytest.approx(20.0)
    assert float(rows["mean_over_10kPa"]["max_rel_err"]) == pytest.approx(0.0)
    assert float(rows["force_over_10kPa"]["level0_kPa"]) == pytest.approx(1000.0)
    assert float(rows["force_over_10kPa"]["max_rel_err"]) == pytest.approx(0.5)
    assert float(rows["regions_csv"]["max_rel_err"]) == pytest.approx(0.0)
    (tmp_path / "fine" / "pressure_facets.npz").unlink()
    p = subprocess.run([sys.executable, str(script), "--runs", "pinch=" + ",".join(folders)],
                       capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert p.returncode != 0 and "fine" in p.stderr and "Traceback" not in p.stderr
