"""``handfe`` command line. Each sub-command lives in ``handfe/commands/<name>.py`` and exposes
``register(subparsers)``; command modules import heavy libraries (dolfinx, gmsh) only inside
their run function so that ``--help`` stays fast."""

from __future__ import annotations

import argparse
import importlib
import sys

from handfe import __version__
from handfe.errors import HandFEError

# Order = order in --help. Add a new command by adding its module name here.
COMMANDS = ("material", "fingertip", "calibrate", "anatomy", "emg", "angles", "run",
            "sensitivity", "demo")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="handfe",
        description="Finite-element simulation of human hand grasps (units: mm, N, MPa, s).",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"handfe {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMANDS:
        try:
            mod = importlib.import_module(f"handfe.commands.{name}")
        except ModuleNotFoundError as exc:
            if exc.name == f"handfe.commands.{name}":
                continue  # not implemented yet
            raise
        mod.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except HandFEError as exc:
        print(f"handfe {args.command}: error: {exc}", file=sys.stderr, flush=True)
        return 2
    except KeyboardInterrupt:
        print(f"handfe {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
