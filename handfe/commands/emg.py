"""``handfe emg``: muscle forces (N) of a grasp from a subject's surface EMG (brief section 2)."""

from __future__ import annotations

import argparse
import sys
import warnings
from pathlib import Path

DESCRIPTION = """\
Muscle forces (N) of one grasp from a subject's surface EMG: zero-phase Butterworth band-pass
(default 20-400 Hz), mains-hum removal, full-wave rectification, linear envelope, MVC
normalisation and F = (EMG / EMG_MVC) * F_MVC, averaged over the grasp's trials (mean +- sample
SD). Settings come from the [emg] table of <subject>/trials.toml (docs/emg.md); the options below
override them. Writes <out>/muscle_forces.csv (muscle, force_N, sd_N, emg_pct_mvc, mvc_force_N,
n_trials). Data layout: subjects/README.md."""


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "emg", help="muscle forces (N) of a grasp from surface EMG",
        description=DESCRIPTION, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--subject", type=Path, required=True,
                   help="subject folder with trials.toml, mvc.csv and emg/ (e.g. subjects/S01)")
    p.add_argument("--grasp", required=True,
                   help="grasp name listed in trials.toml (cylindrical, spherical, precision)")
    p.add_argument("--trial", type=int, default=None,
                   help="process only this trial number (its force; SD reported as 0)")
    p.add_argument("--out", type=Path, default=None,
                   help="output folder (default results/emg/<subject>_<grasp>[_tN])")
    p.add_argument("--plot", action="store_true",
                   help="also write emg_<grasp>_trial<N>.png: raw, band-passed and envelope "
                        "signal per muscle (first trial, or --trial), hold window shaded")
    p.add_argument("--envelope", choices=("lowpass", "rms"), default=None,
                   help="linear envelope: rectify + zero-phase low-pass, or moving RMS "
                        "(default from trials.toml, else lowpass)")
    p.add_argument("--order", type=int, default=None,
                   help="Butterworth band-pass prototype order (2*order poles, applied "
                        "forward-backward; default 4)")
    p.add_argument("--hold", choices=("window", "detect"), default=None,
                   help="hold windows from trials.toml (window) or detected steady holds "
                        "(detect)")
    p.set_defaults(func=run)


def _print_warnings(caught: list[warnings.WarningMessage]) -> None:
    for w in caught:
        print(f"handfe emg: warning: {w.message}", file=sys.stderr)


def run(args: argparse.Namespace) -> int:
    from handfe.emg import process_grasp, read_subject
    from handfe.paths import RESULTS_DIR

    subject = read_subject(args.subject)
    settings = subject.emg_settings(envelope=args.envelope, bandpass_order=args.order,
                                    hold=args.hold)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        res = process_grasp(args.subject, args.grasp, trial=args.trial, settings=settings)
    _print_warnings(caught)
    forces = res.forces()
    norm = res.normalised()
    n = len(res.trials)
    which = f"trial {args.trial}" if args.trial is not None else f"{n} trials, mean +- SD"
    synth = "  [SYNTHETIC demo data]" if subject.synthetic else ""
    print(f"{subject.id} {args.grasp}: muscle forces from EMG ({which}){synth}")
    print(f"  {settings.describe()}")
    print(f"  {'muscle':<7}{'force_N':>10}{'sd_N':>9}{'%MVC':>8}{'F_MVC_N':>10}")
    for m, (f, sd) in forces.items():
        print(f"  {m:<7}{f:>10.2f}{sd:>9.2f}{100 * norm[m]:>8.1f}{res.mvc_force_N[m]:>10.1f}")

    suffix = f"_t{args.trial}" if args.trial is not None else ""
    out = args.out or RESULTS_DIR / "emg" / f"{subject.id}_{args.grasp}{suffix}"
    out.mkdir(parents=True, exist_ok=True)
    csv_path = out / "muscle_forces.csv"
    lines = [f"# handfe emg --subject {args.subject} --grasp {args.grasp}"
             + (f" --trial {args.trial}" if args.trial is not None else ""),
             f"# {settings.describe()}",
             "muscle,force_N,sd_N,emg_pct_mvc,mvc_force_N,n_trials"]
    lines += [f"{m},{f:.3f},{sd:.3f},{100 * norm[m]:.2f},{res.mvc_force_N[m]:.3f},{n}"
              for m, (f, sd) in forces.items()]
    csv_path.write_text("\n".join(lines) + "\n")
    print(f"wrote {csv_path}")
    if args.plot:
        spec = subject.trials(args.grasp, args.trial)[0]
        png = out / f"emg_{args.grasp}_trial{spec.trial}.png"
        _plot(subject, spec, res, png)
        print(f"wrote {png}")
    return 0


def _plot(subject, spec, res, png: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from handfe.emg import _envelopes, read_timeseries

    tr = next(t for t in res.trials if t.trial == spec.trial)
    ts = read_timeseries(tr.file, max_gap_s=res.settings.max_gap_s)
    traces = _envelopes(ts, res.muscles, res.settings)
    fig, axes = plt.subplots(len(res.muscles), 2, figsize=(11, 1.6 * len(res.muscles)),
                             sharex=True, squeeze=False)
    for i, m in enumerate(res.muscles):
        c = traces[m]
        a0, a1 = axes[i]
        a0.plot(c.time, c.raw, lw=0.4, color="0.4")
        a0.set_ylabel(m)
        a1.plot(c.time, c.filtered, lw=0.3, color="tab:blue", label="band-passed")
        a1.plot(c.time, c.envelope, lw=1.2, color="tab:red", label="envelope")
        for a in (a0, a1):
            a.axvspan(*tr.hold_s, color="tab:green", alpha=0.12, lw=0)
        a1.text(0.99, 0.95, f"{tr.force_N[m]:.1f} N ({100 * tr.normalised[m]:.0f} % MVC)",
                transform=a1.transAxes, ha="right", va="top", fontsize=8)
    axes[0, 0].set_title("raw EMG (file units)")
    axes[0, 1].set_title("band-passed, hum removed; envelope (red); hold shaded")
    axes[0, 1].legend(loc="upper left", fontsize=7)
    axes[-1, 0].set_xlabel("time (s)")
    axes[-1, 1].set_xlabel("time (s)")
    fig.suptitle(f"{subject.id} {res.grasp} trial {tr.trial}: {res.settings.describe()}",
                 fontsize=9)
    fig.tight_layout()
    fig.savefig(png, dpi=110)
    plt.close(fig)
