"""``handfe anatomy``: build, pose and mesh the hand of a subject (or import scanned surfaces)."""

from __future__ import annotations

import argparse

HELP = """Build a subject's hand from the anatomy tables, pose it by joint angles and mesh it with
gmsh (tetrahedra), or import a subject's segmented surfaces. Units: mm, degrees.

Writes into --out: hand.xdmf (mesh, cell tags skin=1 subcutaneous=2 nail=3, facet tags: wrist=90
(whole hand, or --digits with --no-skip-far), palm cut=91 (partial hands), skin by region/phalanx
100+10*region+phalanx, bone surfaces 201..227), anatomy.json (bone frames, joints, ligaments,
tendon insertions in the posed frame), quality.json (cells, quality, dihedral angles, volumes,
areas, skin thickness, timings, "skipped": dropped digits and bones and the estimated cells
saved; "from_cache": true if the mesh was read back) and hand.png (palmar view, regions coloured).

Meshes are cached in ~/.cache/handfe/meshes (HANDFE_CACHE_DIR to move it, HANDFE_MESH_CACHE=0
to bypass): the same subject, pose, digits and level are meshed once; a gmsh failure is cached
too and reported at once.
"""


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "anatomy", help="build, pose and mesh a subject's hand (or import scanned surfaces)",
        description=HELP, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--subject", default="subjects/S01", metavar="DIR",
                   help="subject directory holding anthropometry.toml (lengths in mm; "
                        "default: subjects/S01, a 50th-percentile adult male)")
    p.add_argument("--pose", metavar="FILE",
                   help="posture TOML with a table [angles] of DOF = value (degrees for "
                        "rotations, mm for wrist translations; DOF names and limits in "
                        "anatomy/joints.csv). Default: the neutral pose (all zero). Examples: "
                        "anatomy/poses/{cylindrical,spherical,precision}.toml")
    p.add_argument("--digits", metavar="LIST",
                   help="comma-separated digits to mesh (thumb,index,middle,ring,little); the "
                        "palm is cut between kept and dropped fingers so that only the part "
                        "carrying the kept digits is meshed, the proximal carpal row and the "
                        "wrist stub are cut away (cut faces: facet tag 91, no wrist face 90) "
                        "and the mesh is coarse (h_far) away from the kept digits' middle and "
                        "distal segments; quality.json 'skipped' lists what was left out and "
                        "the cells saved. Default: the whole hand")
    p.add_argument("--no-skip-far", dest="skip_far", action="store_false", default=None,
                   help="with --digits: keep the carpus, the wrist stub (tag 90) and the "
                        "level's uniform sizes (only the dropped digits and their palm part "
                        "are left out)")
    p.add_argument("--mesh", default="reduced", choices=("coarse", "reduced", "default", "fine"),
                   help="mesh level: global / fingertip-pad / palm / far (partial hands) "
                        "element size in mm: coarse 4.7/3.0/4.7/5.0 (fast whole-hand tests "
                        "and previews; skin one element thick, not validated for pressures), "
                        "reduced 3.0/2.0/3.0/5.0, default 2.0/1.0/1.6/4.0, fine "
                        "1.4/0.6/1.1/2.8 (default: reduced)")
    p.add_argument("--out", required=True, metavar="DIR", help="output directory (created)")
    p.add_argument("--import", dest="import_skin", metavar="SKIN",
                   help="import path: closed outer skin surface of a subject (STL/OBJ/PLY, mm); "
                        "needs --bones. The skin layer is the --skin-thickness offset inwards")
    p.add_argument("--bones", metavar="DIR",
                   help="with --import: directory of closed bone surfaces named after the bones "
                        "of anatomy/bones.csv (e.g. index_dp.stl), mm")
    p.add_argument("--skin-thickness", type=float, default=None, metavar="MM",
                   help="with --import: skin thickness in mm (default: the subject's value)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from mpi4py import MPI

    from handfe.anatomy import load_subject
    from handfe.errors import InputError
    from handfe.kinematics import Pose
    from handfe.parallel import rprint

    comm = MPI.COMM_WORLD
    if args.import_skin:
        from handfe.anatomy.importer import import_hand
        from handfe.anatomy.outputs import write_outputs

        if not args.bones:
            raise InputError("--import needs --bones DIR (one closed surface per bone)")
        subject = load_subject(args.subject)
        t = args.skin_thickness or subject.hand.skin_thickness_mm
        model = import_hand(args.import_skin, args.bones, skin_thickness_mm=t,
                            level=args.mesh, comm=comm)
        paths = write_outputs(model, args.out)
        rprint(f"imported {args.import_skin}: {model.quality['cells']} tets -> {paths['xdmf']}")
        return 0
    if args.bones:
        raise InputError("--bones is only used with --import SKIN")
    from handfe.anatomy import build_hand, write_outputs

    subject = load_subject(args.subject)
    pose = Pose.from_toml(args.pose) if args.pose else Pose.neutral()
    if args.skip_far is False and not args.digits:
        raise InputError("--no-skip-far is only used with --digits (a partial hand)")
    model = build_hand(subject, pose, digits=args.digits, level=args.mesh, comm=comm,
                       skip_far=args.skip_far)
    paths = write_outputs(model, args.out)
    q = model.quality
    rprint(f"{subject.subject} {','.join(model.digits)} ({args.mesh}): {q['cells']} tets, "
           f"min quality {q['min_quality']:.3f}, hand volume {q['hand_volume_cm3']:.0f} cm3, "
           f"meshing {q['meshing_time_s']:.1f} s -> {paths['xdmf'].parent}")
    sk = q.get("skipped", {})
    if sk.get("digits"):
        rprint(f"skipped: digits {','.join(sk['digits'])}, {len(sk['bones'])} bones; "
               f"{q['cells']} tets = {sk['fraction_of_whole_hand']:.2f} x the whole hand "
               f"(estimated {sk['cells_whole_hand_estimate']})")
    return 0
