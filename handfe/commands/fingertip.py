"""``handfe fingertip``: flat-plate compression of the index fingertip (brief §3)."""

from __future__ import annotations

import argparse

from handfe.fingertip import MESH_LEVELS

HELP = """\
A rigid plate at ANGLE degrees to the finger axis is pushed against the pad of an index
fingertip (geometry from reference/fingertip_anthropometry.csv; distal phalanx rigid and fixed,
nail linear elastic E = 170 MPa, soft tissue hyperelastic, near-incompressible, Taylor-Hood P2-P1
by default). Contact: augmented Lagrangian, penetration <= 0.01 mm at the end, Coulomb friction.
By default only half the fingertip is solved (sagittal symmetry plane, u_y = 0 there); all
reported numbers are the whole fingertip's. The gmsh mesh is cached in ~/.cache/handfe/meshes
(HANDFE_CACHE_DIR to move it, HANDFE_MESH_CACHE=0 to bypass).

Writes into --out:
  summary.json   force_N, deflection_mm (plate travel after first contact), contact_area_mm2
                 (pad area within --gap-tol of the plate: lumped nodal area over the
                 P2 nodes, docs/contact.md), contact_length_mm / contact_width_mm
                 (extent along / across the finger axis in the plate plane), mean_pressure_kPa,
                 peak_pressure_kPa, max_penetration_mm, load_steps, newton_iterations, dofs,
                 wall_s, h_mm / h_pad_mm (element sizes), and the material used
  fields.xdmf    displacement (mm) and contact pressure (kPa) for ParaView (with the default
                 --model half: the half y >= 0; use ParaView's Reflect filter, plane Y)
  pressure.png   contact pressure on the pad seen through the plate, colour bar in kPa
  sweep.csv      with --sweep: force, area, length, width, peak pressure at every load step

Examples:
  handfe fingertip --angle 15 --force 4 --out results/fingertip_4N
  mpirun -n 2 handfe fingertip --angle 30 --indent 2.5 --mesh reduced --sweep --out results/ft
"""


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("fingertip", help="fingertip plate compression (contact pressure, area, "
                       "deflection)", description=HELP,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--angle", type=float, default=15.0,
                   help="plate angle to the finger axis, degrees in 0..90 (default 15)")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--force", type=float, help="target plate force, N (reached to 0.5 %%)")
    g.add_argument("--indent", type=float, help="plate travel after first contact, mm "
                   "(displacement control)")
    p.add_argument("--mesh", choices=("coarse", "reduced", "default", "fine"), default="default",
                   help="mesh level, global / pad element size: "
                        + ", ".join(f"{k} {h:g} / {hp:g} mm" for k, (h, hp) in MESH_LEVELS.items())
                        + " (default: default, within 2 %% of fine in deflection and area at "
                        "4 N, see README; coarse is for fast tests only, not validated)")
    p.add_argument("--h", type=float, default=None, metavar="MM",
                   help="global element size in mm (overrides --mesh; pad is 0.6x finer "
                        "unless --h-pad is given)")
    p.add_argument("--h-pad", type=float, default=None, metavar="MM",
                   help="element size on the pad in mm (0.2..the global size; default: the "
                        "level's, or 0.6 x --h). The contact area converges with the pad size, "
                        "the deflection with the global size (docs/contact.md)")
    p.add_argument("--element", choices=("taylor-hood", "p1-p0", "p2", "p1"),
                   default="taylor-hood",
                   help="FE element (default taylor-hood P2-P1 mixed; p1-p0 = P1 + DG0 pressure, "
                        "cheap; p1 locks, for comparison)")
    p.add_argument("--model", choices=("half", "full"), default="half",
                   help="half (default): mesh only y >= 0 and hold u_y = 0 on the sagittal "
                        "symmetry plane (exact: geometry and plate load are symmetric; half the "
                        "dofs); every reported number "
                        "is the whole fingertip's, the fields are the half (ParaView: Reflect). "
                        "full: the whole fingertip")
    p.add_argument("--subject", default="mean",
                   help="anthropometry row: mean (default) or S1..S5")
    p.add_argument("--material", default=None, metavar="NAME",
                   help="pulp material: 'calibrated' (default: the fit of `handfe calibrate "
                        "fingertip`), 'published' (brief's Mooney-Rivlin fit), 'ogden-skin', "
                        "'ogden-subcutaneous', or LAW:PRESET (e.g. neo-hookean:subcutaneous)")
    p.add_argument("--layered", action="store_true",
                   help="skin layer over subcutaneous tissue instead of a homogeneous pulp")
    p.add_argument("--skin-thickness", type=float, default=1.0, metavar="MM",
                   help="skin layer thickness with --layered, mm (default 1.0)")
    p.add_argument("--friction", type=float, default=0.74,
                   help="Coulomb friction coefficient skin-plate (default 0.74; 0 = frictionless)")
    p.add_argument("--gap-tol", type=float, default=0.01, metavar="MM",
                   help="gap within which pad counts as in contact for the area, mm (0.01)")
    p.add_argument("--sweep", action="store_true",
                   help="record the force/area/deflection curve at every load step (sweep.csv)")
    p.add_argument("--out", default="results/fingertip", help="output folder")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    p.set_defaults(func=run)


def material_from_name(name: str | None):
    from handfe.errors import InputError
    from handfe.materials import MooneyRivlin, Ogden, preset

    if name in (None, "calibrated"):
        return None
    if name == "published":
        return MooneyRivlin.fingertip_mean()
    if name == "ogden-skin":
        return Ogden.skin()
    if name == "ogden-subcutaneous":
        return Ogden.subcutaneous()
    if ":" in name:
        law, pre = name.split(":", 1)
        return preset(law, pre)
    raise InputError(f"--material '{name}': use calibrated, published, ogden-skin, "
                     "ogden-subcutaneous or LAW:PRESET")


def run(args: argparse.Namespace) -> int:
    import json
    from dataclasses import asdict
    from pathlib import Path

    from mpi4py import MPI

    from handfe.errors import InputError
    from handfe.fingertip import mesh_sizes
    from handfe.fingertip_scene import FingertipConfig
    from handfe.fingertip_scene import run as run_scene
    from handfe.parallel import rprint

    if args.force is None and args.indent is None:
        raise InputError("give --force N or --indent MM")
    if args.force is not None and not args.force > 0:
        raise InputError(f"--force {args.force:g}: the plate force must be positive (N)")
    if args.indent is not None and not args.indent > 0:
        raise InputError(f"--indent {args.indent:g}: the plate travel must be positive (mm)")
    try:  # the sizes are checked again where the mesh is made; here with the flags' names
        mesh_sizes(args.mesh, args.h, args.h_pad)
    except InputError as exc:
        raise InputError(str(exc).replace("h_pad_mm", "--h-pad").replace("h_mm", "--h")
                         ) from None
    cfg = FingertipConfig(subject=args.subject, angle_deg=args.angle, mesh=args.mesh,
                          h_mm=args.h, h_pad_mm=args.h_pad, element=args.element,
                          material=material_from_name(args.material), layered=args.layered,
                          skin_thickness_mm=args.skin_thickness, friction=args.friction,
                          gap_tol_mm=args.gap_tol, half_model=args.model == "half")
    out = Path(args.out)
    progress = None if args.quiet else (lambda s: rprint(s))
    what = f"{args.force:g} N" if args.force is not None else f"{args.indent:g} mm"
    rprint(f"handfe fingertip: plate at {args.angle:g} deg, {what}, mesh {args.mesh}, "
           f"{MPI.COMM_WORLD.size} rank(s)")
    res = run_scene(cfg, force_N=args.force, indent_mm=args.indent, sweep=args.sweep,
                    out_dir=out, progress=progress)
    d = asdict(res)
    d.pop("sweep")
    keys = ("force_N", "deflection_mm", "contact_area_mm2", "contact_length_mm",
            "contact_width_mm", "mean_pressure_kPa", "peak_pressure_kPa", "max_penetration_mm",
            "load_steps", "newton_iterations", "dofs", "wall_s")
    rprint(json.dumps({k: d[k] for k in keys}, indent=1))
    rprint(f"handfe fingertip: results in {out.resolve()}")
    return 0
