"""``handfe angles``: the 27 joint angles of a grasp from a subject's data-glove recordings."""

from __future__ import annotations

import argparse
from pathlib import Path

DESCRIPTION = """\
Joint angles of one grasp from a subject's data-glove recordings: raw sensor counts through the
linear calibration of trials.toml [glove] (or angle columns in degrees), every sample checked
against the joint limits of anatomy/joints.csv, averaged over each trial's hold window and over
trials (mean +- sample SD). DOFs the glove does not measure are at their neutral value. Writes
<out>/joint_angles.csv (dof, unit, mean, sd, measured, n_trials) and <out>/pose.toml, readable by
handfe.kinematics.Pose.from_toml. Data layout: subjects/README.md."""


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "angles", help="joint angles (deg) of a grasp from data-glove recordings",
        description=DESCRIPTION, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--subject", type=Path, required=True,
                   help="subject folder with trials.toml and glove/ (e.g. subjects/S01)")
    p.add_argument("--grasp", required=True,
                   help="grasp name listed in trials.toml (cylindrical, spherical, precision)")
    p.add_argument("--trial", type=int, default=None,
                   help="use only this trial number (SD reported as 0)")
    p.add_argument("--out", type=Path, default=None,
                   help="output folder (default results/angles/<subject>_<grasp>[_tN])")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from handfe.emg import read_subject
    from handfe.kinematics import grasp_angles, joint_table
    from handfe.paths import RESULTS_DIR

    subject = read_subject(args.subject)
    res = grasp_angles(args.subject, args.grasp, trial=args.trial)
    pose = res.pose()
    ms = res.mean_sd()
    n = len(res.trials)
    which = f"trial {args.trial}" if args.trial is not None else f"{n} trials, mean +- SD"
    synth = "  [SYNTHETIC demo data]" if subject.synthetic else ""
    print(f"{subject.id} {args.grasp}: joint angles from the data glove ({which}){synth}")
    print("  averaged over each trial's hold window; '-' = not measured (neutral)")
    print(f"  {'dof':<22}{'mean':>9}{'sd':>7}  unit")
    table = joint_table()
    for name, (m, sd) in ms.items():
        tag = f"{sd:>7.2f}" if name in res.measured else f"{'-':>7}"
        print(f"  {name:<22}{m:>9.2f}{tag}  {table[name].unit}")

    suffix = f"_t{args.trial}" if args.trial is not None else ""
    out = args.out or RESULTS_DIR / "angles" / f"{subject.id}_{args.grasp}{suffix}"
    out.mkdir(parents=True, exist_ok=True)
    csv_path = out / "joint_angles.csv"
    lines = [f"# handfe angles --subject {args.subject} --grasp {args.grasp}"
             + (f" --trial {args.trial}" if args.trial is not None else ""),
             "dof,unit,mean,sd,measured,n_trials"]
    lines += [f"{k},{table[k].unit},{m:.3f},{sd:.3f},{int(k in res.measured)},{n}"
              for k, (m, sd) in ms.items()]
    csv_path.write_text("\n".join(lines) + "\n")
    toml_path = pose.write_toml(out / "pose.toml", f"{subject.id} {args.grasp} from the data "
                                f"glove ({which}), handfe angles")
    print(f"wrote {csv_path}\nwrote {toml_path}")
    return 0
