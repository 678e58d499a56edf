"""``handfe calibrate fingertip``: fit the pulp material to the 15-degree deflections."""

from __future__ import annotations

import argparse

HELP = """\
Fits the fingertip pulp law W = C01 (Ib2-3) + C20 (Ib1-3)^2 + (1/D1)(J-1)^2 (nu = 0.49999 by
default: near-incompressible, Drucker-stable over the scene's strains), to the
15-degree plate compression of brief §3 (2.8 mm at 2 N, 3.1 mm at 4 N) and only to those data.
Writes the fitted parameters, the predicted deflections and the residual to
reference/fingertip_calibrated_material.json (or --out), which `handfe fingertip` then uses as
its default material. Method and the reason for the law: handfe/calibration.py.
"""


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("calibrate", help="fit the fingertip pulp material to the 15-degree data",
                       description=HELP, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("scene", choices=("fingertip",), help="what to calibrate")
    p.add_argument("--mesh", choices=("coarse", "reduced", "default", "fine"), default="reduced",
                   help="mesh level of the fitting solves (default reduced)")
    p.add_argument("--h", type=float, default=None, metavar="MM", help="element size (mm)")
    p.add_argument("--max-sweeps", type=int, default=10,
                   help="largest number of force-deflection sweeps (default 10)")
    p.add_argument("--nu", type=float, default=None,
                   help="Poisson's ratio of the pulp, fixed during the fit (default 0.49999; "
                        "0.49 gives a Drucker-unstable compressible set, docs/materials.md)")
    p.add_argument("--ratio", type=float, default=None,
                   help="hold C20/C01 at this value (dimensionless) and fit only the scale: "
                        "one sweep instead of a search over the ratio")
    p.add_argument("--out", default=None,
                   help="output JSON (default reference/fingertip_calibrated_material.json)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from dataclasses import asdict
    from pathlib import Path

    from mpi4py import MPI

    from handfe.calibration import CALIBRATION_NU, calibrate
    from handfe.fingertip_scene import CALIBRATION_FILE
    from handfe.io import write_json
    from handfe.parallel import rprint

    nu = CALIBRATION_NU if args.nu is None else args.nu
    rprint(f"handfe calibrate fingertip: fitting C01, C20 (nu = {nu:g}) to 2.8 mm @ 2 N and "
           "3.1 mm @ 4 N, plate at 15 deg")
    res = calibrate(mesh=args.mesh, h_mm=args.h, max_sweeps=args.max_sweeps, nu=nu,
                    ratio=args.ratio, progress=lambda s: rprint(s))
    out = Path(args.out) if args.out else CALIBRATION_FILE
    if MPI.COMM_WORLD.rank == 0:
        data = {"law": "mooney-rivlin",
                "parameters": {"C10_MPa": 0.0, "C01_MPa": res.C01_MPa, "C20_MPa": res.C20_MPa,
                               "nu": res.nu},
                "fit": asdict(res),
                "data": "reference/fingertip_compression_15deg.csv (15 deg only)",
                "command": f"handfe calibrate fingertip --mesh {args.mesh} --nu {nu:g}"
                           + (f" --h {args.h:g}" if args.h else "")
                           + (f" --ratio {args.ratio:g}" if args.ratio else "")}
        write_json(out, data)
    pred = ", ".join(f"{x:.3f}" for x in res.predicted_mm)
    rprint(f"C01 = {res.C01_MPa * 1e3:.4f} kPa, C20 = {res.C20_MPa * 1e3:.4f} kPa "
           f"(C20/C01 = {res.ratio:.3g}); deflections {pred}"
           f" mm vs measured {', '.join(f'{x:.2f}' for x in res.measured_mm)} mm; rms "
           f"{res.residual_mm:.4f} mm; {res.sweeps} sweeps, {res.wall_s:.0f} s")
    rprint(f"wrote {out}")
    return 0
