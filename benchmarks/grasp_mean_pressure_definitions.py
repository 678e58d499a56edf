"""Would another mean-pressure definition converge with the mesh? (issue 6)

For each digit (thumb..little) of finished ``handfe run`` folders of one grasp at several mesh
levels (coarsest first, the last is the reference), compare the mean contact pressure as
regions.csv reports it (``mean_pressure_kPa``: normal load over the tributary area of the nodes
at >= 1 % of the skin's peak) with two threshold-based ones computed from the run's
``pressure_facets.npz``: the area-weighted mean of the nodal pressures over the vertices at
>= T kPa (the loaded area's vertices), and the digit's normal force over that loaded area.
Digits carrying < 0.5 N in the reference are left out. Prints CSV: one row per grasp, digit,
definition, with each level's value (kPa) and the largest relative error against the last
level. No solve; a few seconds.

    .venv/bin/python benchmarks/grasp_mean_pressure_definitions.py \
        --runs pinch=PC,PR,PD --runs sphere=SC,SR,SD --thresholds 5,10,20
"""

from __future__ import annotations

import argparse
import csv
import sys
from pathlib import Path

import numpy as np

from handfe.grasp.outputs import facet_areas, load_pressure_facets, loaded_area, region_of

DIGITS = ("thumb", "index", "middle", "ring", "little")
MIN_FORCE_N = 0.5


def digit_means(folder: Path, thresholds: list[float]) -> dict[str, dict[str, float]]:
    """Per digit: {definition: kPa} and ``normal_force_N`` for one run folder."""
    try:
        with open(folder / "regions.csv", newline="") as fh:
            rows = {r["region"]: r for r in csv.DictReader(fh)}
        data, _, _ = load_pressure_facets(folder / "pressure_facets.npz")
    except (OSError, ValueError, KeyError) as exc:
        raise SystemExit(f"--runs {folder}: not a finished run folder ({exc})") from None
    area = facet_areas(data["xf"])
    p = data["p_kPa"]
    reg = np.array([region_of(c)[0] for c in data["codes"]])
    out: dict[str, dict[str, float]] = {}
    for d in DIGITS:
        if d not in rows:
            raise SystemExit(f"--runs {folder}: regions.csv has no row '{d}'")
        m = reg == d
        fn = float(rows[d]["normal_force_N"])
        vals = {"regions_csv": float(rows[d]["mean_pressure_kPa"]), "normal_force_N": fn}
        for t in thresholds:
            # the loaded area as regions.csv defines it; the mean weights each loaded vertex's
            # pressure by the same third of its facets
            al = float(loaded_area(area[m], p[m], t).sum())
            psum = float(((p[m] * (p[m] >= t)).sum(axis=1) * area[m] / 3.0).sum())
            vals[f"mean_over_{t:g}kPa"] = psum / al if al > 0 else 0.0
            vals[f"force_over_{t:g}kPa"] = 1e3 * fn / al if al > 0 else 0.0
        out[d] = vals
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--runs", action="append", required=True, metavar="GRASP=DIR,DIR,...",
                    help="run folders of one grasp, coarsest first; the last is the reference "
                         "(repeat for more grasps)")
    ap.add_argument("--thresholds", default="5,10,20",
                    help="pressure thresholds (kPa) of the loaded area, comma-separated "
                         "(default 5,10,20)")
    args = ap.parse_args(argv)
    try:
        thresholds = [float(t) for t in args.thresholds.split(",")]
    except ValueError:
        raise SystemExit(f"--thresholds {args.thresholds!r}: not numbers") from None
    if any(t <= 0 for t in thresholds):
        raise SystemExit(f"--thresholds {args.thresholds!r}: must be > 0 kPa")
    w = csv.writer(sys.stdout, lineterminator="\n")
    header_done = False
    for spec in args.runs:
        grasp, sep, dirs = spec.partition("=")
        folders = [Path(x) for x in dirs.split(",") if x]
        if not sep or len(folders) < 2:
            raise SystemExit(f"--runs {spec!r}: expected GRASP=DIR,DIR[,...] (two or more)")
        levels = [digit_means(f, thresholds) for f in folders]
        if not header_done:
            w.writerow(["grasp", "digit", "definition", *[f"level{i}_kPa" for i in
                        range(len(folders))], "max_rel_err"])
            header_done = True
        ref = levels[-1]
        for d in DIGITS:
            if ref[d]["normal_force_N"] < MIN_FORCE_N:
                continue
            for key in ref[d]:
                if key == "normal_force_N":
                    continue
                vals = [lv[d][key] for lv in levels]
                err = max(abs(v / vals[-1] - 1) for v in vals[:-1]) if vals[-1] > 0 \
                    else float("nan")
                w.writerow([grasp, d, key, *[f"{v:.1f}" for v in vals], f"{err:.3f}"])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
