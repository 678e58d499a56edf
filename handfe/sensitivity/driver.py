"""Sensitivity driver: the baseline and one-parameter-at-a-time cases, run concurrently over MPI
groups, each finished case written atomically to ``<out>/cases/<case-id>.json``.

* **Groups.** ``COMM_WORLD`` (or the ``comm`` given) is split into groups of ``ranks_per_case``
  ranks (color = rank // ranks_per_case); each group runs one case at a time on its own
  communicator. Assignment is static round-robin over the pending cases (case k -> group
  k mod n_groups), the same under ``mpirun`` and a cluster launcher.
* **Nothing lost.** The group leader writes each case file as soon as the case ends (temp file +
  rename). A case whose runner raises an ``Exception`` is written with status ``failed`` and its
  error; the others go on. A re-run skips cases already on disk with status ``ok`` or
  ``skipped`` and the same fingerprint (kind, mesh, scene/workflow content, parameter, level,
  refit settings); ``failed`` cases and stale ones are run again; ``force=True`` re-runs all.
* **Tables** come only from the files on disk (:mod:`handfe.sensitivity.tables`), so an
  interrupted study, re-run, ends with the same tables as an uninterrupted one.
* **Material cases** carry a refit (:mod:`handfe.sensitivity.refit`); an unusable refit (poor or
  Drucker-unstable) is not run with ``refit.policy = "skip"`` (status ``skipped``), or run and
  flagged with ``policy = "run"``.

Case runners: ``RUNNERS[kind](study, spec, comm) -> dict`` returning
``{"regions": {region: {metric: value}}, "info": {...}}``; the grasp runner imports
:mod:`handfe.grasp` lazily.
"""

from __future__ import annotations

import hashlib
import json
import math
import sys
import time
import traceback
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

from handfe.errors import InputError
from handfe.materials import Ogden
from handfe.sensitivity.study import MATERIAL_PARAMETERS, Study

BASELINE = "baseline"
SCHEMA = 1


@dataclass(frozen=True)
class Case:
    """One run: ``parameter`` perturbed by ``level_pct`` % (the baseline: "baseline", 0)."""

    parameter: str
    level_pct: float

    @property
    def id(self) -> str:
        return case_id(self.parameter, self.level_pct)

    @property
    def delta(self) -> float:
        return self.level_pct / 100.0


def case_id(parameter: str, level_pct: float) -> str:
    """File-name-safe id: ``baseline``, ``skin_m10``, ``FDS_p20``, ``force_p2.5``."""
    if parameter == BASELINE:
        return BASELINE
    sign = "p" if level_pct > 0 else "m"
    return f"{parameter}_{sign}{abs(level_pct):g}"


def study_cases(study: Study) -> list[Case]:
    """The baseline first, then each parameter's levels in ascending order."""
    out = [Case(BASELINE, 0.0)]
    for p in study.parameters:
        out.extend(Case(p, float(lv)) for lv in study.levels(p))
    return out


@dataclass
class CaseSpec:
    """What a runner gets: tissue laws, muscle-force factors, load factor, refit info."""

    case: Case
    materials: dict[str, Ogden]
    muscle_scale: dict[str, float] = field(default_factory=dict)
    load_scale: float = 1.0
    refit: dict[str, Any] | None = None
    problem: str = ""
    #: the case's progress log (``OUT/cases/<case-id>.log``), written by a runner that has
    #: progress lines (the grasp's: a case runs for minutes); None = no log
    log_path: str | None = None


def baseline_materials(study: Study) -> dict[str, Ogden]:
    nu = study.refit.tissue_nu
    return {"skin": Ogden.skin(nu=nu), "subcutaneous": Ogden.subcutaneous(nu=nu)}


def make_spec(study: Study, case: Case) -> CaseSpec:
    """Inputs of one case (computes the material refit for a material parameter)."""
    from handfe.sensitivity.refit import refit_scaled

    mats = baseline_materials(study)
    spec = CaseSpec(case, mats)
    p = case.parameter
    if p == BASELINE:
        return spec
    if p in MATERIAL_PARAMETERS:
        rs = study.refit
        r = refit_scaled(mats[p], case.delta, tissue=p, fit_stretch=rs.fit_stretch,
                         n_points=rs.n_points, stability_stretch=rs.stability_stretch,
                         n_starts=rs.n_starts, max_fit_error_pct=rs.max_fit_error_pct)
        spec.refit = r.to_dict()
        spec.problem = r.problem
        if sum(r.mu_MPa) > 0.0:
            mats[p] = r.material()
    elif study.kind == "fingertip" and p == "force":
        spec.load_scale = 1.0 + case.delta
    else:
        spec.muscle_scale = {p: 1.0 + case.delta}
    return spec


def fingerprint(study: Study, case: Case) -> str:
    """Hash of everything that determines a case's result (a stale file is re-run)."""
    d: dict[str, Any] = {"schema": SCHEMA, "kind": study.kind, "mesh": study.mesh,
                         "parameter": case.parameter, "level_pct": case.level_pct,
                         "tissue_nu": study.refit.tissue_nu}
    if study.kind == "fingertip":
        from handfe.fingertip_scene import FingertipConfig

        # the scene's model (half since Dec 2026): case files of the whole model re-run
        d["fingertip"] = {**asdict(study.fingertip), "half_model": FingertipConfig().half_model}
    else:
        d["workflow"] = study.workflow_digest()
        if study.loading is not None:  # absent key: fingerprints of older case files hold
            d["loading"] = study.loading
    if case.parameter in MATERIAL_PARAMETERS:
        d["refit"] = asdict(study.refit)
    return hashlib.sha256(json.dumps(d, sort_keys=True, default=str).encode()).hexdigest()[:16]


# --------------------------------------------------------------------------------------------
# Case runners
# --------------------------------------------------------------------------------------------
def run_fingertip_case(study: Study, spec: CaseSpec, comm) -> dict[str, Any]:
    """Layered fingertip (skin over subcutaneous, both Ogden) pressed by the plate."""
    from handfe.fingertip_scene import FingertipCompression, FingertipConfig

    ft = study.fingertip
    cfg = FingertipConfig(angle_deg=ft.angle_deg, mesh=ft.mesh, h_mm=ft.h_mm,
                          element=ft.element, layered=True,
                          skin_thickness_mm=ft.skin_thickness_mm,
                          material=spec.materials["subcutaneous"],
                          skin_material=spec.materials["skin"], friction=ft.friction,
                          # the contact scheme this study was validated with (before the
                          # pressure-following penalty and augmented friction, which failed
                          # 2 of its cases under MPI: not investigated yet)
                          adaptive_penalty=None, augmented_friction=False,
                          newton_linesearch="bt", march_tol_factor=1.0)
    t0 = time.perf_counter()
    scene = FingertipCompression(cfg, comm=comm)
    scene.push_to_force(ft.force_N * spec.load_scale, rtol=ft.force_rtol)
    res = scene.result(time.perf_counter() - t0)
    pad = {k: float(getattr(res, k)) for k in
           ("contact_area_mm2", "mean_pressure_kPa", "peak_pressure_kPa", "deflection_mm",
            "force_N", "tangential_force_N", "contact_length_mm", "contact_width_mm",
            "max_penetration_mm")}
    return {"regions": {"pad": pad},
            "info": {"force_target_N": ft.force_N * spec.load_scale, "dofs": res.dofs,
                     "cells": res.cells, "newton_iterations": res.newton_iterations,
                     "load_steps": res.load_steps, "mesh": res.mesh}}


def _case_log(path: str | None, comm) -> Callable[[str], None] | bool:
    """The progress callback of a case: the file ``path`` is started afresh, then each line,
    with the seconds since the case started, is appended by the case's rank 0 (``tail -f``
    it); False without a path."""
    if path is None:
        return False
    t0 = time.perf_counter()
    if comm.rank == 0:
        Path(path).write_text("")

    def say(msg: str) -> None:
        if comm.rank == 0:
            with open(path, "a") as fh:
                fh.write(f"[{time.perf_counter() - t0:7.1f} s] {msg}\n")

    return say


def run_grasp_case(study: Study, spec: CaseSpec, comm) -> dict[str, Any]:
    """A grasp workflow (handfe.grasp, imported here) with tissue laws / muscle factors."""
    from handfe.grasp import load_workflow, run_workflow

    wf = load_workflow(study.workflow_path())
    # the workflow's Poisson's ratio for the tissue (the refit is incompressible, nu-free)
    nu = getattr(getattr(wf, "solver", None), "nu", None)
    mats = {k: (Ogden(m.mu_MPa, m.alpha, nu=float(nu)) if nu is not None else m)
            for k, m in spec.materials.items()}
    res = run_workflow(wf, mesh=study.mesh, out_dir=None, comm=comm, materials=mats,
                       muscle_scale=spec.muscle_scale or None, loading=study.loading,
                       progress=_case_log(spec.log_path, comm))
    regions = {str(r): {str(k): float(v) for k, v in m.items()
                        if isinstance(v, int | float) and not isinstance(v, bool)}
               for r, m in res.regions.items()}
    summary = json.loads(json.dumps(res.summary, default=str))
    if isinstance(summary, dict) and summary.get("status") not in (None, "ok", "done"):
        raise RuntimeError(f"grasp workflow ended with status {summary.get('status')!r}")
    return {"regions": regions, "info": {"tissue_nu": nu, "summary": summary}}


RUNNERS: dict[str, Callable[[Study, CaseSpec, Any], dict[str, Any]]] = {
    "fingertip": run_fingertip_case, "grasp": run_grasp_case}


# --------------------------------------------------------------------------------------------
# Files
# --------------------------------------------------------------------------------------------
def case_path(out_dir: Path, cid: str) -> Path:
    return Path(out_dir) / "cases" / f"{cid}.json"


def read_case(out_dir: Path, cid: str) -> dict[str, Any] | None:
    """The stored case record, or None if absent or unreadable."""
    p = case_path(out_dir, cid)
    try:
        return json.loads(p.read_text())
    except (OSError, ValueError):
        return None


def is_done(rec: dict[str, Any] | None, fp: str) -> bool:
    return bool(rec) and rec.get("fingerprint") == fp and rec.get("status") in ("ok", "skipped")


def _materials_dict(mats: dict[str, Ogden]) -> dict[str, Any]:
    return {k: {"mu_MPa": list(m.mu_MPa), "alpha": list(m.alpha), "nu": m.nu}
            for k, m in mats.items()}


def execute_case(study: Study, case: Case, comm, *, runner=None,
                 log_path: Path | None = None) -> dict[str, Any]:
    """Run one case on ``comm`` (collective) and return its record (JSON-able). Exceptions of
    the runner are caught and recorded; the record is meaningful on every rank. ``log_path``:
    where a runner with progress lines (the grasp's) writes them."""
    t0 = time.perf_counter()
    rec: dict[str, Any] = {"schema": SCHEMA, "study": study.name, "kind": study.kind,
                           "case_id": case.id, "parameter": case.parameter,
                           "level_pct": case.level_pct, "fingerprint": fingerprint(study, case),
                           "mesh": study.mesh, "ranks": comm.size}
    spec = None
    err = None
    try:
        spec = comm.bcast(make_spec(study, case) if comm.rank == 0 else None, root=0)
    except Exception as exc:  # noqa: BLE001 - recorded, the study goes on
        err = exc
    if spec is not None and log_path is not None:
        spec = replace(spec, log_path=str(log_path))
    if spec is not None:
        rec.update(inputs={"materials": _materials_dict(spec.materials),
                           "muscle_scale": spec.muscle_scale, "load_scale": spec.load_scale},
                   refit=spec.refit, flag=spec.problem)
    status, out, tb = "ok", None, ""
    if err is None and spec is not None and spec.problem and study.refit.policy == "skip":
        status = "skipped"
    elif err is None:
        try:
            out = (runner or RUNNERS[study.kind])(study, spec, comm)
        except Exception as exc:  # noqa: BLE001 - recorded, the study goes on
            err = exc
    if err is not None:
        tb = "".join(traceback.format_exception(err)[-4:])
    errs = comm.allgather(None if err is None else f"{type(err).__name__}: {err}")
    first = next((e for e in errs if e), None)
    if first:
        status, out = "failed", None
        rec["error"] = first
        rec["traceback"] = tb
    rec["status"] = status
    rec["regions"] = (out or {}).get("regions", {})
    rec["info"] = (out or {}).get("info", {})
    rec["wall_s"] = comm.allreduce(time.perf_counter() - t0, op=_max_op())
    rec["finished_utc"] = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
    return rec


def _max_op():
    from mpi4py import MPI

    return MPI.MAX


def _fmt_s(s: float) -> str:
    s = max(0.0, s)
    h, r = divmod(int(round(s)), 3600)
    m, sec = divmod(r, 60)
    return f"{h}h{m:02d}m{sec:02d}s" if h else f"{m}m{sec:02d}s"


@dataclass
class StudyRun:
    """What :func:`run_study` returns (identical on every rank)."""

    out_dir: Path
    total: int
    reused: int
    ran: int
    statuses: dict[str, str]
    tables: dict[str, str]
    wall_s: float


def run_study(study: Study, out_dir: Path | str, *, comm=None, ranks_per_case: int = 1,
              force: bool = False, progress: bool = True, runner=None, charts: bool = True,
              file=None) -> StudyRun:
    """Run the pending cases of ``study`` into ``out_dir`` and build the tables (collective on
    ``comm``, default COMM_WORLD). ``runner`` replaces ``RUNNERS[study.kind]`` (tests);
    ``charts=False`` skips the tornado PNGs."""
    from mpi4py import MPI

    comm = comm or MPI.COMM_WORLD
    out_dir = Path(out_dir)
    file = file or sys.stdout
    size = comm.size
    if ranks_per_case < 1 or size % ranks_per_case:
        raise InputError(f"--ranks-per-case {ranks_per_case}: must be >= 1 and divide the "
                         f"number of MPI ranks ({size})")
    t0 = time.perf_counter()
    cases = study_cases(study)
    by_id = {c.id: c for c in cases}
    if comm.rank == 0:
        (out_dir / "cases").mkdir(parents=True, exist_ok=True)
        pending = [c.id for c in cases
                   if force or not is_done(read_case(out_dir, c.id), fingerprint(study, c))]
    else:
        pending = None
    pending = comm.bcast(pending, root=0)
    n_groups = size // ranks_per_case
    color = comm.rank // ranks_per_case
    gcomm = comm.Split(color, comm.rank)
    mine = pending[color::n_groups]
    reused = len(cases) - len(pending)

    def say(msg: str) -> None:
        if comm.rank == 0 and progress:
            print(f"[sensitivity {study.name}] {msg}", file=file, flush=True)

    say(f"{len(cases)} cases, {reused} already on disk, {len(pending)} to run on {n_groups} "
        f"group(s) of {ranks_per_case} rank(s); out: {out_dir}")
    start_stamp = time.time()

    def report(last: str = "") -> None:
        if comm.rank != 0 or not progress:
            return
        done = sum(1 for cid in pending if _finished_since(out_dir, cid, start_stamp))
        el = time.perf_counter() - t0
        eta = el / done * (len(pending) - done) if done else math.nan
        est = _fmt_s(eta) if math.isfinite(eta) else "?"
        say(f"{done}/{len(pending)} cases done ({reused + done}/{len(cases)} in all), "
            f"elapsed {_fmt_s(el)}, estimate {est} left{'; ' + last if last else ''}")

    try:
        for cid in mine:
            rec = execute_case(study, by_id[cid], gcomm, runner=runner,
                               log_path=case_path(out_dir, cid).with_suffix(".log"))
            if gcomm.rank == 0:
                from handfe.io import write_json

                write_json(case_path(out_dir, cid), rec)
            msg = f"{cid}: {rec['status']} in {rec['wall_s']:.1f} s"
            if rec["status"] == "failed":
                msg += f" ({rec.get('error', '')})"
                if gcomm.rank == 0:
                    print(f"[sensitivity {study.name}] case {cid} FAILED: {rec.get('error')}",
                          file=sys.stderr, flush=True)
            report(msg)
    finally:
        gcomm.Free()
    # wait for the other groups without spinning (cores are shared), rank 0 reporting progress
    req = comm.Ibarrier()
    last_done = -1
    while not req.Test():
        time.sleep(0.25)
        if comm.rank == 0 and progress:
            done = sum(1 for cid in pending if _finished_since(out_dir, cid, start_stamp))
            if done != last_done and last_done >= 0:
                report()
            last_done = done
    tables: dict[str, str] = {}
    statuses: dict[str, str] = {}
    if comm.rank == 0:
        from handfe.sensitivity.tables import build_tables

        tables, statuses = build_tables(study, out_dir, charts=charts)
        n_bad = sum(1 for s in statuses.values() if s != "ok")
        say(f"done in {_fmt_s(time.perf_counter() - t0)}: "
            + ", ".join(f"{k} {v}" for k, v in sorted(_count(statuses).items()))
            + (f"; {n_bad} case(s) not ok, see status.csv" if n_bad else ""))
    tables, statuses = comm.bcast((tables, statuses), root=0)
    return StudyRun(out_dir=out_dir, total=len(cases), reused=reused, ran=len(pending),
                    statuses=statuses, tables=tables,
                    wall_s=comm.allreduce(time.perf_counter() - t0, op=_max_op()))


def _count(statuses: dict[str, str]) -> dict[str, int]:
    out: dict[str, int] = {}
    for s in statuses.values():
        out[s] = out.get(s, 0) + 1
    return out


def _finished_since(out_dir: Path, cid: str, stamp: float) -> bool:
    try:
        return case_path(out_dir, cid).stat().st_mtime >= stamp - 1.0
    except OSError:
        return False
