"""``handfe material``: closed-form and FE stress of a law under homogeneous deformation."""

from __future__ import annotations

import argparse
import sys

HELP = """\
Nominal (first Piola-Kirchhoff) stress of a hyperelastic law under a homogeneous deformation,
as CSV on stdout with columns

  stretch                 applied stretch lambda (-)
  nominal_stress_MPa      closed form P11 = dW/dlambda along the mode's path (MPa = N/mm^2)
  tangent_MPa             dP11/dlambda along the path (MPa)
  stable                  1 if the tangent is positive (Drucker-stable in this mode), else 0
  fe_nominal_stress_MPa   the same stress from an FE solve of a 1 mm cube (reaction / area)

Modes: uniaxial (lambda, s, s), equibiaxial (lambda, lambda, s; P11 = P22 reported) and
shear = pure shear / planar tension (lambda, 1, s). The free stretch s makes the free faces
traction-free, or is fixed by J = 1 with --incompressible. confined = uniaxial strain
(lambda, 1, 1; J = lambda): a tissue layer squeezed between a bone and an object, where
the law's bulk modulus carries most of the load. Tension is positive.

Examples:
  handfe material ogden --preset skin --mode uniaxial --stretch 0.6:1.6:11 --incompressible
  handfe material mooney-rivlin --preset fingertip --mode equibiaxial --stretch 0.7:1.3:7
  handfe material neo-hookean --param E_MPa=0.05 --param nu=0.45 --mode shear --stretch 1:2:5
  handfe material ogden --preset subcutaneous --drucker 0.5:2.0
  handfe material ogden --preset subcutaneous --param nu=0.499 --mode confined --stretch 0.1:1:10
"""


def register(sub: argparse._SubParsersAction) -> None:
    from handfe.materials import HOMOGENEOUS_MODES, PRESETS

    p = sub.add_parser("material", help="stress-stretch curves of a material law (closed form "
                       "and FE)", description=HELP,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("law", choices=sorted(PRESETS), help="material law")
    p.add_argument("--preset", help="literature parameter set: " + "; ".join(
        f"{law}: {', '.join(names)}" for law, names in PRESETS.items()))
    p.add_argument("--param", action="append", default=[], metavar="NAME=VALUE",
                   help="override a parameter (MPa for moduli), e.g. mu_MPa=-0.07,0.011,0.066 "
                        "alpha=4.9,6.4,4.7 nu=0.49 C01_MPa=0.0006; for neo-hookean and "
                        "st-venant-kirchhoff E_MPa and nu may be given instead of mu/lmbda")
    p.add_argument("--mode", choices=HOMOGENEOUS_MODES, default="uniaxial",
                   help="deformation mode (default uniaxial); confined = uniaxial strain "
                        "(lambda, 1, 1), a tissue layer squeezed between bone and object, "
                        "compressible laws only")
    p.add_argument("--stretch", default="0.6:1.6:11", metavar="START:STOP:N",
                   help="N stretches evenly from START to STOP (default 0.6:1.6:11), or a "
                        "comma-separated list")
    p.add_argument("--incompressible", action="store_true",
                   help="exact incompressibility (J = 1; mixed FE with 1/kappa = 0)")
    p.add_argument("--element", choices=("taylor-hood", "p2", "p1"), default=None,
                   help="FE element for the cube (default taylor-hood, p2 for laws without a "
                        "volumetric split)")
    p.add_argument("--no-fe", action="store_true", help="skip the FE column (closed form only)")
    p.add_argument("--drucker", metavar="LO:HI", default=None,
                   help="instead of the CSV, report where dP/dlambda <= 0 in each mode for "
                        "stretches LO..HI")
    p.set_defaults(func=run)


def parse_stretches(text: str) -> list[float]:
    from handfe.errors import InputError

    try:
        if ":" in text:
            a, b, n = text.split(":")
            import numpy as np

            if int(n) < 1:
                raise ValueError
            vals = [float(x) for x in np.linspace(float(a), float(b), int(n))]
        else:
            vals = [float(x) for x in text.split(",")]
    except ValueError:
        raise InputError(f"--stretch '{text}': expected START:STOP:N or a comma list of "
                         "numbers") from None
    bad = [v for v in vals if not v > 0.0]
    if bad:
        raise InputError(f"--stretch '{text}': stretch {bad[0]:g} must be positive")
    return vals


def build_material(law: str, preset: str | None, params: list[str]):
    from handfe.errors import InputError
    from handfe.materials import LAWS
    from handfe.materials import preset as get_preset

    over: dict[str, object] = {}
    for item in params:
        if "=" not in item:
            raise InputError(f"--param '{item}': expected NAME=VALUE")
        k, v = item.split("=", 1)
        try:
            vals = tuple(float(x) for x in v.split(","))
        except ValueError:
            raise InputError(f"--param {k}: '{v}' is not a number or comma list") from None
        over[k.strip()] = vals if len(vals) > 1 or k.strip() in ("mu_MPa", "alpha") else vals[0]
    cls = LAWS[law]
    if "E_MPa" in over or ("nu" in over and hasattr(cls, "from_E_nu") and preset is None):
        if not hasattr(cls, "from_E_nu"):
            raise InputError(f"{law}: E_MPa is not a parameter of this law")
        try:
            return cls.from_E_nu(float(over.pop("E_MPa")), float(over.pop("nu", 0.3)))
        except KeyError:
            raise InputError(f"{law}: give E_MPa (and nu) or mu_MPa and lmbda_MPa") from None
    if preset is not None:
        mat = get_preset(law, preset)
        return mat.with_params(**over) if over else mat
    try:
        return cls(**over)
    except TypeError as exc:
        raise InputError(f"{law}: no --preset given and the parameters are incomplete ({exc})") \
            from None


def run(args: argparse.Namespace) -> int:
    from mpi4py import MPI

    from handfe.errors import InputError
    from handfe.materials import drucker_stability, homogeneous, tangent

    mat = build_material(args.law, args.preset, args.param)
    comm = MPI.COMM_WORLD
    out = sys.stdout
    if args.drucker:
        try:
            lo, hi = (float(x) for x in args.drucker.split(":"))
        except ValueError:
            raise InputError(f"--drucker '{args.drucker}': expected LO:HI") from None
        rep = drucker_stability(mat, stretch_range=(lo, hi), incompressible=args.incompressible)
        if comm.rank == 0:
            print(rep.describe(), file=out)
        return 0
    lams = parse_stretches(args.stretch)
    rows = []
    for lam in lams:
        P, _ = homogeneous(mat, args.mode, lam, incompressible=args.incompressible)
        T = tangent(mat, args.mode, lam, incompressible=args.incompressible)
        rows.append((lam, P, T, int(T > 0.0)))
    fe = [float("nan")] * len(lams)
    if not args.no_fe:
        from handfe.solver import Discretisation
        from handfe.verification import cube_stress_curve

        disc = Discretisation(args.element) if args.element else None
        fe = list(cube_stress_curve(mat, args.mode, lams, incompressible=args.incompressible,
                                    disc=disc, comm=comm))
    if comm.rank == 0:
        print("stretch,nominal_stress_MPa,tangent_MPa,stable,fe_nominal_stress_MPa", file=out)
        for (lam, P, T, s), f in zip(rows, fe, strict=True):
            print(f"{lam:.6g},{P:.12e},{T:.12e},{s},{f:.12e}", file=out)
    return 0
