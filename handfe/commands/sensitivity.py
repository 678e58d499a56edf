"""``handfe sensitivity``: one-at-a-time sensitivity study of tissue laws and muscle forces."""

from __future__ import annotations

import argparse

HELP = """\
Runs a sensitivity study (brief §1): the baseline once, then each parameter of the study file
changed alone by each level (% of its baseline value). Parameters: 'skin' / 'subcutaneous'
(the uniaxial nominal stress of the tissue's Ogden N=3 set scaled by 1 + level at fixed strain,
then re-fitted by least squares; a poor or Drucker-unstable refit is flagged and, by default,
not run), a muscle name (FDS, FDP, AP, FPB, ...: that muscle force x (1 + level)) for grasp
studies with muscle-driven loading (study or workflow key loading = "muscles"; the kinematic
closing never reads the muscle forces, so such a study is refused), or 'force' (plate force)
for fingertip studies.

Cases run concurrently: the MPI ranks are split into groups of --ranks-per-case ranks, one case
per group. Each finished case is written at once to OUT/cases/<case-id>.json (metrics, refit,
wall time, error if it failed); a grasp case's progress lines go to OUT/cases/<case-id>.log
while it runs. Re-running skips finished cases (unless --force), so an interrupted study is
resumed by running the same command again. Failed cases are recorded and retried on the next
run; the others go on.

Writes into OUT (built from the case files only):
  table_<parameter>.csv   rows = metric x region; columns baseline, then per level the value and
                          its % change from baseline
  sensitivity_long.csv    parameter, level_pct, region, metric, value, pct_change,
                          ratio_of_pct_change (= % change of output / % change of input), ...
  refits.csv              refitted Ogden mu_i (MPa), alpha_i, fit residual (%), Drucker stable
  status.csv              every case: status (ok/failed/skipped/missing), wall time (s), error
  tornado_<metric>.png    % change per parameter at its lowest/highest level, per region

Units: areas mm^2, pressures kPa, forces N, deflection mm, levels and changes in %.

Examples:
  handfe sensitivity sensitivity/fingertip_small.toml --out results/sensitivity/fingertip_small
  mpirun -n 2 handfe sensitivity sensitivity/cylindrical_fdp.toml \\
      --out results/sensitivity/cylindrical_fdp
"""


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("sensitivity", help="one-at-a-time sensitivity study (materials, muscle "
                       "forces), parallel and resumable", description=HELP,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("study", metavar="STUDY.toml", help="study definition (see sensitivity/)")
    p.add_argument("--mesh", default=None, metavar="LEVEL",
                   help="mesh level override for every case (grasp: passed to the workflow, "
                        "e.g. reduced; fingertip: coarse|reduced|default|fine, replaces the "
                        "study's mesh and h_mm). Default: the study's setting")
    p.add_argument("--ranks-per-case", type=int, default=1, metavar="N",
                   help="MPI ranks per case (must divide the number of ranks; default 1: "
                        "as many concurrent cases as ranks)")
    p.add_argument("--force", action="store_true",
                   help="re-run every case even if its file is already in OUT/cases")
    p.add_argument("--out", default=None, metavar="DIR",
                   help="output folder (default results/sensitivity/<study name>)")
    p.add_argument("--tables-only", action="store_true",
                   help="do not run anything: rebuild the tables/charts from OUT/cases")
    p.add_argument("--quiet", action="store_true", help="no progress lines")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from mpi4py import MPI

    from handfe.parallel import rprint
    from handfe.paths import RESULTS_DIR
    from handfe.sensitivity import build_tables, load_study, run_study

    study = load_study(args.study).with_mesh(args.mesh)
    out = Path(args.out) if args.out else RESULTS_DIR / "sensitivity" / study.name
    comm = MPI.COMM_WORLD
    if args.tables_only:
        if comm.rank == 0:
            if not (out / "cases").is_dir():
                from handfe.errors import InputError

                raise InputError(f"--tables-only: {out / 'cases'} does not exist")
            paths, statuses = build_tables(study, out)
            bad = {k: v for k, v in statuses.items() if v != "ok"}
            rprint(f"tables rebuilt in {out} ({len(statuses) - len(bad)}/{len(statuses)} "
                   "cases ok)")
        return 0
    res = run_study(study, out, comm=comm, ranks_per_case=args.ranks_per_case,
                    force=args.force, progress=not args.quiet)
    n_failed = sum(1 for s in res.statuses.values() if s == "failed")
    rprint(f"tables in {out}: " + ", ".join(sorted(Path(p).name for p in res.tables.values())))
    return 1 if n_failed else 0
