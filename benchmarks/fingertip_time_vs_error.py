"""Fingertip scene: run time against error (issue 3).

4 N at 15 degrees, several element sizes (global / pad) and both element families; error of
deflection, contact area and peak pressure against the finest taylor-hood run (smallest global
size, then smallest pad size). Wall time: median of --repeats runs (each run
builds the mesh and solves; JIT compilation is excluded by a warm-up run per element). The
machine may be shared: each row also records the process CPU time (s, this rank) and the
1-minute load average at the start of the run, so inflated wall times can be recognised.
--budget-s stops starting new runs once the budget is spent (the CSV is rewritten after every
point, so a cut-short benchmark still leaves its rows).

    mpirun -n 2 .venv/bin/python benchmarks/fingertip_time_vs_error.py --elements taylor-hood \
        --repeats 3 --max-repeat-s 60 --out results/bench_fingertip     # ~17 min, 10 of them
                                                                        # the 1.0 / 0.45 reference
    mpirun -n 2 .venv/bin/python benchmarks/fingertip_time_vs_error.py --sizes 3:1.5,2.5:1 \
        --elements taylor-hood --repeats 1                              # quick look

Writes CSV (stdout and OUT/fingertip_time_vs_error.csv) and OUT/fingertip_time_vs_error.png
(errors against the finest taylor-hood run; dashed line 2 %, dotted line 20 s).
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
from pathlib import Path

from mpi4py import MPI

from handfe.fingertip import PAD_SIZE_RATIO
from handfe.fingertip_scene import FingertipConfig, run
from handfe.io import write_csv
from handfe.parallel import rprint

METRICS = ("deflection_mm", "contact_area_mm2", "peak_pressure_kPa")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--force", type=float, default=4.0, help="plate force, N (default 4)")
    ap.add_argument("--angle", type=float, default=15.0, help="plate angle, deg (default 15)")
    ap.add_argument("--model", choices=("half", "full"), default="half",
                    help="half (default, the scene's default: y >= 0 with u_y = 0 on the "
                         "symmetry plane) or full fingertip")
    ap.add_argument("--sizes",
                    default="3.5:1.5,2.5:1.5,3.5:1.0,2.5:1.0,2.0:1.0,2.5:0.75,1.5:0.9,1.0:0.45",
                    help="element sizes, mm, coarse to fine: H (pad 0.6 H) or H:PAD (global "
                         "size H, pad size PAD), comma-separated")
    ap.add_argument("--elements", default="taylor-hood,p1-p0",
                    help="element families, comma-separated (taylor-hood, p1-p0, p2, p1)")
    ap.add_argument("--budget-s", type=float, default=None,
                    help="wall-time budget, s: no new run is started after it is spent")
    ap.add_argument("--no-warmup", action="store_true",
                    help="skip the untimed warm-up solve per element (forms already cached)")
    ap.add_argument("--repeats", type=int, default=3, help="timed runs per point (median)")
    ap.add_argument("--max-repeat-s", type=float, default=None,
                    help="no repeats for a point whose first run took longer than this (s): "
                         "the fine reference levels are then timed once (column 'runs')")
    ap.add_argument("--out", default="results/bench_fingertip", help="output folder")
    ap.add_argument("--from-csv", default=None,
                    help="no runs: recompute the errors and redraw the PNG from this CSV")
    a = ap.parse_args()
    comm = MPI.COMM_WORLD
    if a.from_csv:
        import csv

        if comm.rank == 0:
            with open(a.from_csv) as f:
                report(list(csv.DictReader(f)), Path(a.out), f"fingertip (from {a.from_csv})")
        return
    sizes = [parse_size(x) for x in a.sizes.split(",")]
    half = a.model == "half"
    rows = []
    t_start = time.perf_counter()
    out = Path(a.out)

    def over_budget() -> bool:
        spent = comm.bcast(time.perf_counter() - t_start, root=0)
        return a.budget_s is not None and spent > a.budget_s

    for el in a.elements.split(","):
        if over_budget():
            break
        if not a.no_warmup:
            # warm-up: compile this element's forms once (not timed)
            run(FingertipConfig(angle_deg=a.angle, h_mm=max(s[0] for s in sizes), element=el,
                                half_model=half),
                force_N=min(a.force, 1.0), comm=comm)
        for h, pad in sizes:
            times, cpus, loads, solves, res = [], [], [], [], None
            for _ in range(a.repeats):
                # rank 0's time decides, so every rank stops at the same point
                if times and (over_budget() or (a.max_repeat_s is not None and comm.bcast(
                        times[0], root=0) > a.max_repeat_s)):
                    break
                loads.append(os.getloadavg()[0])
                t0, c0 = time.perf_counter(), time.process_time()
                res = run(FingertipConfig(angle_deg=a.angle, h_mm=h, h_pad_mm=pad, element=el,
                                          half_model=half), force_N=a.force, comm=comm)
                times.append(time.perf_counter() - t0)
                solves.append(res.solve_s)
                cpus.append(time.process_time() - c0)
            if res is None:
                break
            row = {"element": el, "model": a.model, "h_mm": h, "h_pad_mm": res.h_pad_mm,
                   "area_method": res.area_method, "dofs": res.dofs,
                   "cells": res.cells, "runs": len(times),
                   "wall_s_median": statistics.median(times),
                   "solve_s_median": statistics.median(solves), "mesh_s": res.mesh_s,
                   "cpu_s_median": statistics.median(cpus), "load_avg_1min": max(loads),
                   "newton_iterations": res.newton_iterations, "load_steps": res.load_steps,
                   "uzawa_updates": res.uzawa_updates, "force_N": res.force_N,
                   **{m: getattr(res, m) for m in METRICS},
                   "max_penetration_mm": res.max_penetration_mm, "ranks": comm.size}
            rows.append(row)
            rprint(f"# {el} h={h} pad={res.h_pad_mm:g}: {row}")
            if comm.rank == 0:
                out.mkdir(parents=True, exist_ok=True)
                write_csv(out / "fingertip_time_vs_error.csv", rows)
            if over_budget():
                break
    if comm.rank == 0 and rows:
        report(rows, out, f"fingertip, {a.force:g} N at {a.angle:g} deg, {comm.size} rank(s)")


def parse_size(text: str) -> tuple[float, float | None]:
    """'H' -> (H, None: the scene's pad size PAD_SIZE_RATIO x H); 'H:PAD' -> (H, PAD), mm."""
    h, _, pad = text.strip().partition(":")
    return float(h), (float(pad) if pad else None)


def _fineness(r: dict) -> tuple[float, float]:
    """Sort key, finest first: global size, then pad size (rows of older CSVs without one:
    the scene's PAD_SIZE_RATIO x h)."""
    h = float(r["h_mm"])
    pad = r.get("h_pad_mm")
    return h, float(pad) if pad not in (None, "") else PAD_SIZE_RATIO * h


def report(rows: list[dict], out: Path, title: str) -> None:
    """Errors, CSV and PNG. Two references: the finest run of the same element
    (``err_<metric>_pct``: self-convergence) and the finest taylor-hood run
    (``err_<metric>_vs_ref_pct``: the accuracy that counts; p1-p0 locks, so its
    self-convergence says little)."""
    for r in rows:
        r["h_mm"], r["wall_s_median"] = float(r["h_mm"]), float(r["wall_s_median"])
        for m in METRICS:
            r[m] = float(r[m])
    th = [r for r in rows if r["element"] == "taylor-hood"] or rows
    best = min(th, key=_fineness)
    for el in {r["element"] for r in rows}:
        mine = sorted((r for r in rows if r["element"] == el), key=_fineness)
        ref = mine[0]
        for r in mine:
            for m in METRICS:
                r[f"err_{m}_pct"] = 100.0 * abs(r[m] - ref[m]) / abs(ref[m])
                r[f"err_{m}_vs_ref_pct"] = 100.0 * abs(r[m] - best[m]) / abs(best[m])
    out.mkdir(parents=True, exist_ok=True)
    write_csv(out / "fingertip_time_vs_error.csv", rows)
    print((out / "fingertip_time_vs_error.csv").read_text())
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axs = plt.subplots(1, 3, figsize=(13, 4), dpi=110)
    for ax, m in zip(axs, METRICS, strict=True):
        for el in sorted({r["element"] for r in rows}):
            pts = [(r["wall_s_median"], r[f"err_{m}_vs_ref_pct"], _label(r)) for r in rows
                   if r["element"] == el and r is not best]
            if pts:
                ax.loglog([p[0] for p in pts], [max(p[1], 1e-2) for p in pts], "o-", label=el)
                for p in pts:
                    ax.annotate(p[2], (p[0], max(p[1], 1e-2)), fontsize=7)
        ax.axhline(2.0, color="0.5", ls="--", lw=0.8)
        ax.axvline(20.0, color="0.5", ls=":", lw=0.8)
        ax.set_xlabel("wall time, median (s)")
        ax.set_ylabel(f"error of {m} (%)")
        ax.legend(fontsize=8)
    fig.suptitle(f"{title}; reference: taylor-hood {_label(best)} mm "
                 f"({best['wall_s_median']:.0f} s)")
    fig.tight_layout()
    fig.savefig(out / "fingertip_time_vs_error.png")


def _label(r: dict) -> str:
    h, pad = _fineness(r)
    return f"h={h:g}/{pad:g}"


if __name__ == "__main__":
    main()
