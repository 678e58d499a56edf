"""``handfe demo``: the main job on its default, small settings."""

from __future__ import annotations

import argparse


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("demo", help="run the main demo on small settings and say where the "
                       "results are", description="Runs the most complete workflow available "
                       "on its default small settings and writes results under results/demo.")
    p.add_argument("--out", default=None, help="output folder (default results/demo)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import importlib
    from pathlib import Path

    from mpi4py import MPI

    from handfe.paths import RESULTS_DIR

    out = Path(args.out) if args.out else RESULTS_DIR / "demo"
    comm = MPI.COMM_WORLD
    if comm.rank == 0:
        out.mkdir(parents=True, exist_ok=True)
    comm.barrier()
    steps = []
    # the furthest stage of the pipeline that exists is run; earlier stages are quick checks
    if importlib.util.find_spec("handfe.commands.run") and (
            Path(__file__).resolve().parents[2] / "workflows" / "cylindrical.toml").exists():
        # the whole-hand cylindrical grasp at the workflow's level, reduced (93k dofs): 10-12 min
        # on 2 idle cores (6-7 Dec 2026, README); `handfe run ... --mesh coarse` takes ~8 min
        wf = str(Path(__file__).resolve().parents[2] / "workflows" / "cylindrical.toml")
        steps.append(("cylindrical power grasp, whole hand, reduced mesh", [
            "run", wf, "--mesh", "reduced", "--out", str(out / "cylindrical")]))
    elif importlib.util.find_spec("handfe.commands.fingertip"):
        steps.append(("fingertip compression, 15 deg, 2 N", [
            "fingertip", "--angle", "15", "--force", "2", "--mesh", "reduced", "--out",
            str(out / "fingertip")]))
    from handfe.cli import main

    steps.insert(0, ("skin law: closed form vs FE cube", [
        "material", "ogden", "--preset", "skin", "--mode", "uniaxial", "--stretch",
        "0.6:1.6:11", "--incompressible"]))
    for title, argv in steps:
        if comm.rank == 0:
            print(f"== {title}: handfe {' '.join(argv)}", flush=True)
        if argv[0] == "material":
            import contextlib
            import io

            buf = io.StringIO()
            with contextlib.redirect_stdout(buf):  # every rank solves; rank 0 prints
                code = main(argv)
            if comm.rank == 0:
                (out / "ogden_skin_uniaxial.csv").write_text(buf.getvalue())
                print(buf.getvalue(), end="")
        else:
            code = main(argv)
        if code:
            return code
    if comm.rank == 0:
        print(f"\nhandfe demo: results are in {out.resolve()}")
    return 0
