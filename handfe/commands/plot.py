"""``handfe plot``: draw a grasp run's palmar pressure map again from its run folder."""

from __future__ import annotations

import argparse

HELP = """\
Draw the palmar contact pressure map of a finished `handfe run` again, without re-running:
from the skin facets the run kept in RUN/pressure_facets.npz (deformed positions in mm, vertex
contact pressures in kPa, region codes). Use it to put several runs on one colour scale
(--vmax), e.g. a coarse and a reduced run of the same grasp, or to write the picture elsewhere.

Examples:
  handfe plot results/cylindrical                       # rewrites results/cylindrical/pressure.png
  handfe plot results/cyl_coarse --vmax 300 --out coarse.png
"""


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("plot", help="redraw a grasp run's pressure map (common colour scale)",
                       description=HELP, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("run_dir", help="output folder of a `handfe run`")
    p.add_argument("--vmax", type=float, default=None, metavar="KPA",
                   help="top of the colour scale in kPa (default: the run's largest pressure)")
    p.add_argument("--out", default=None, metavar="PNG",
                   help="picture to write (default: RUN_DIR/pressure.png)")
    p.add_argument("--title", default=None, help="title (default: the run's)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from handfe.errors import InputError
    from handfe.grasp.outputs import draw_pressure_map, load_pressure_facets

    if args.vmax is not None and not args.vmax > 0:
        raise InputError(f"--vmax {args.vmax:g}: the top of the colour scale must be > 0 kPa")
    src = Path(args.run_dir) / "pressure_facets.npz"
    if not src.is_file():
        raise InputError(f"{src}: not found - give the output folder of a `handfe run` made "
                         "with outputs.png = true (runs before 2 Dec 2026 did not keep it)")
    try:
        data, hand_R, title = load_pressure_facets(src)
    except (OSError, KeyError, ValueError) as exc:
        raise InputError(f"{src}: not a pressure-facet file of `handfe run` ({exc})") from exc
    out = Path(args.out) if args.out else Path(args.run_dir) / "pressure.png"
    vmax = draw_pressure_map(data, hand_R, out, title=args.title or title, vmax_kPa=args.vmax)
    print(f"wrote {out} (colour scale 0-{vmax:.0f} kPa, {len(data['codes'])} skin facets)")
    return 0
