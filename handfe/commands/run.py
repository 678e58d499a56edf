"""``handfe run``: a whole-hand grasp workflow (issue 6)."""

from __future__ import annotations

import argparse

HELP = """\
Run a grasp workflow (workflows/*.toml: subject + grasp + loading + mesh level + outputs).

The hand is meshed in the subject's measured grasp posture (glove angles, or the grasp's pose
file) with only the participating digits; the rigid object (grasps/*.toml) is placed in the grasp
cavity just short of contact. Bones are rigid and move as boundary conditions; skin and
subcutaneous tissue are Ogden N=3 (near-incompressible; element p1-p1s: P1 displacement +
stabilised continuous P1 pressure, solver.stabilisation_modulus "initial", "tangent" or
"pressure");
contact is augmented-Lagrangian (penetration <= 0.01 mm) with Coulomb friction (mu 0.74).

Loading:
  muscles  EXPERIMENTAL: the coarse cylinder (workflows/cylindrical_muscles.toml) balances
           the full EMG load to a relative torque residual < 1e-3 with the pads within
           0.01 mm and the object in equilibrium to 2e-14 (status "done" in runs Q and Q2
           with this file's keys, 15-16 min on 2 cores, and L and M before them), with
           solver.tangent_predictor, solver.inversion_guard, solver.muscle_final_uzawa =
           "interleaved", solver.friction_smoothing and solver.muscle_uzawa_max_mm (set
           there; off by default); at mesh reduced with solver.guard_damping and
           solver.muscle_stall_rtol = 3e-4 more (workflows/cylindrical_muscles_reduced.toml,
           "done" in 46 min). Earlier runs ended "unbalanced" (object vs support 6e-5
           where the final FE solves stalled) or failed in the final Uzawa phase; with
           that recipe the ball balanced the full load but failed its final Uzawa phase;
           with solver.inversion_guard = 0.5 and solver.muscle_stall_rtol = 1e-3 more it
           ran to the end in one of two whole runs (workflows/spherical_muscles.toml, "done"
           in 38 min at coarse; the other failed after 68 min);
           the pinch reached 38-53 % of it, its index pad sliding at the friction
           limit (docs/grasp.md);
           a run that gives up writes the last balanced load's results, marked partial;
           docs/grasp.md (README: Grasp status).
           After the angles-mode closing (frictionless by default),
           the EMG muscle forces act as joint torques through their moment arms
           (anatomy/moment_arms.csv), ramped up from the torques that hold the closed posture,
           and the released flexion angles are solved so that muscle + ligament +
           tissue/contact torques balance at every joint (relative residual <= 1e-3);
           solver.dip_pip_coupling (default 2/3) ties each DIP to its PIP; the object is
           held (its support takes the net force); solver.free_object = true solves its
           translation too (no stable pinch with the nine flexor-side muscles: docs/grasp.md).
           muscle_force_scale (default 1) multiplies every EMG muscle force: a lighter grip
           than measured (e.g. --set muscle_force_scale=0.1); at 0.1 the pinch and the ball
           run to the end at coarse (workflows/precision_muscles_light.toml, 4 min, and
           spherical_muscles_light.toml, 11 min, on 2 cores). tendon_split: how FDS's and
           FDP's forces split between digits 2-5: "equal" (default, 1/4 each) or
           "holzbaur2005" (each compartment's peak isometric force: little finger FDS 0.11,
           FDP 0.29; anatomy/tendon_splits.csv)
  angles   (default) each participating digit closes from the pre-closed posture until it
           presses with solver.digit_force_N (at most solver.closing_deg), then Uzawa updates
           bring the penetration to <= 0.01 mm. solver.palm_force_N > 0 (experimental, off)
           first moves the held object along the digits' push into the palm until the palm
           carries that force (summary.json palm_press; docs/grasp.md)

Workflow file: subject, grasp, trial, loading, muscle_force_scale, tendon_split, mesh,
element, base; tables [solver] and [outputs] (each key with its range and why:
handfe/grasp/config.py; an unknown key or a value out of range is refused, naming the file
and the key). base = "NAME" (a workflow in workflows/, or a path relative to the file or
to the repository) starts from every key of that workflow; the file's own keys replace
them, [solver] and [outputs] key by key (e.g. workflows/cylindrical_muscles_reduced.toml =
cylindrical_muscles.toml + 3 keys). --set KEY=VALUE changes a key for one run without a
file; --show prints every key a run would use.

Writes into --out (rank 0):
  regions.csv     per region (thumb, index, middle, ring, little, palm, and each digit's
                  proximal/middle/distal segment): contact_area_mm2 (skin within
                  solver.gap_tol_mm of the object), loaded_area_mm2 (nodal pressure >=
                  outputs.loaded_area_kPa, default 10; far less mesh-dependent, README),
                  mean_pressure_kPa, peak_pressure_kPa, normal_force_N, tangential_force_N
  fingertips.csv  mean and peak contact pressure, contact and loaded area on the five pads
  summary.json    grip force, equilibrium vs measured angles, torque residuals, max penetration,
                  dofs, load steps, Newton iterations, wall time per stage, what was skipped,
                  peak memory (the largest rank's peak resident set, GB); the object is held
                  in space, and net_object_force_N is what its support takes (the digits'
                  forces do not balance each other: 5-21 N at 5 N per digit, README); with
                  solver.free_object (muscles mode) it is ~0 and the object moves;
                  settings: every key the run used (the file's, its base's, the defaults,
                  with --mesh and --loading applied)
  fields.xdmf     displacement (mm), contact pressure (MPa), strain energy density (ParaView)
  pressure.png    palmar-view contact pressure map (kPa), regions outlined
  pressure_facets.npz  the skin facets of that map: `handfe plot RUN` redraws it (--vmax)
At the end the command prints the six regions' rows of regions.csv (contact and loaded area
mm2, mean and peak pressure kPa, normal and tangential force N; not with --quiet).
Exit status: 0 for status "done"; 1 for "unbalanced" (the results are written, but the
object's force and the support reactions differ by more than 1e-6 relative - the last Newton
solve stopped at an accepted stall; summary.json final_residual_N says how far - or, muscles
mode, a released joint's relative torque residual is above solver.torque_rtol;
summary.json balance_problems says which); 2 for a failed
run, which writes summary.json with status "failed", the failed stage and the error (a
muscles run also writes the last balanced load's results, marked "partial").

Examples:
  handfe run workflows/cylindrical.toml --mesh reduced --out results/cylindrical
  mpirun -n 2 handfe run workflows/precision.toml --out results/precision
  handfe run spherical --mesh coarse --set solver.digit_force_N=2.0 --out results/ball_2N
  handfe run cylindrical_muscles_reduced --show
"""


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("run", help="run a grasp workflow (per-region contact pressure/area)",
                       description=HELP, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("workflow", help="workflow TOML (path, or a name in workflows/)")
    p.add_argument("--mesh", choices=("coarse", "reduced", "default", "fine"), default=None,
                   help="mesh level, overrides the workflow's (coarse: tests/previews only; "
                   "time against error per level: README, benchmarks/grasp_time_vs_error.py)")
    p.add_argument("--loading", choices=("muscles", "angles"), default=None,
                   help="loading mode, overrides the workflow's (angles refuses a workflow "
                        "with muscle_force_scale, tendon_split or solver.free_object off its "
                        "default, muscles one with solver.palm_force_N: it would drop them)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="change one workflow key for this run, over the file's (repeatable; "
                   "the value is read as TOML, a bare word as a string), e.g. --set "
                   "solver.guard_damping=true --set solver.muscle_stall_rtol=3e-4; checked "
                   "like a key in the file; summary.json settings keeps what the run used")
    p.add_argument("--show", action="store_true",
                   help="print every key the run would use (the workflow's, its base's, the "
                   "defaults, --set) as a workflow TOML, and exit without running")
    p.add_argument("--out", help="output folder (created; needed unless --show)")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import sys
    from dataclasses import replace
    from pathlib import Path

    from handfe.errors import InputError
    from handfe.grasp import load_workflow, run_workflow
    from handfe.grasp.config import parse_overrides, workflow_toml
    from handfe.grasp.outputs import region_table
    from handfe.parallel import rprint

    wf = load_workflow(args.workflow, parse_overrides(args.set) if args.set else None)
    if args.mesh or args.loading:
        wf = replace(wf, mesh=args.mesh or wf.mesh, loading=args.loading or wf.loading)
    if args.show:
        rprint(workflow_toml(wf), end="")
        return 0
    if not args.out:
        raise InputError("--out is required (the output folder), unless --show")
    res = run_workflow(wf, out_dir=Path(args.out), progress=not args.quiet)
    if not args.quiet:
        skipped = res.summary.get("skipped", {}).get("digits", [])
        rprint(region_table(res.regions, skipped) + f"\n(every region and segment: "
               f"{args.out}/regions.csv; pads: fingertips.csv; the rest: summary.json)")
    status = res.summary.get("status")
    if status == "done":
        return 0
    # "unbalanced": results written but not a converged state; said even with --quiet
    rprint(f"handfe run: {args.workflow}: status {status!r}, equilibrium error "
           f"{res.summary.get('equilibrium_relative_error', float('nan')):.2g}: the results in "
           f"{args.out} are not a converged solution", file=sys.stderr)
    return 1
