"""``handfe`` command line. Each sub-command lives in ``handfe/commands/<name>.py`` and exposes
``register(subparsers)``; command modules import heavy libraries (dolfinx, gmsh) only inside
their run function so that ``--help`` stays fast."""

from __future__ import annotations

import argparse
import importlib
import os
import sys
import time

from handfe import __version__
from handfe.errors import HandFEError

# Order = order in --help. Add a new command by adding its module name here.
COMMANDS = ("material", "fingertip", "calibrate", "anatomy", "emg", "angles", "run", "plot",
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


_ERROR_TAG = 7771  # point-to-point tag of the error handshake (collectives cannot be used: a
# rank-local error leaves the other ranks inside some other collective call)


def _report_error(message: str, grace_s: float = 2.0) -> None:
    """Print ``message`` to stderr once per job. Serial: print; raised before MPI started
    (argument checks, the same on every rank): rank 0 of the launch prints. Otherwise every
    failing rank tells rank 0 (point-to-point): if all ranks report within ``grace_s`` (an
    input error, checked on every rank), rank 0 alone prints it. A rank whose error the others
    do not share prints it with its rank and aborts the job, which would otherwise hang in the
    next collective call of the ranks that go on."""
    MPI = sys.modules.get("mpi4py.MPI")
    if MPI is None or not MPI.Is_initialized() or MPI.Is_finalized():
        # raised before MPI started (argument checks): the same on every rank of a launch
        rank = os.environ.get("OMPI_COMM_WORLD_RANK") or os.environ.get("PMI_RANK") or "0"
        if rank == "0":
            print(message, file=sys.stderr, flush=True)
        return
    comm = MPI.COMM_WORLD
    if comm.size == 1:
        print(message, file=sys.stderr, flush=True)
        return
    if comm.rank == 0:
        deadline = time.monotonic() + grace_s
        pending = set(range(1, comm.size))
        while pending and time.monotonic() < deadline:
            for r in [r for r in pending if comm.Iprobe(source=r, tag=_ERROR_TAG)]:
                comm.recv(source=r, tag=_ERROR_TAG)
                pending.discard(r)
            time.sleep(0.01)
        if not pending:
            print(message, file=sys.stderr, flush=True)
            for r in range(1, comm.size):
                comm.send(True, dest=r, tag=_ERROR_TAG)
            return
    else:
        comm.isend(True, dest=0, tag=_ERROR_TAG)
        deadline = time.monotonic() + 2.0 * grace_s  # rank 0 may have failed a little later
        while time.monotonic() < deadline:
            if comm.Iprobe(source=0, tag=_ERROR_TAG):
                comm.recv(source=0, tag=_ERROR_TAG)
                return
            time.sleep(0.01)
    print(f"[rank {comm.rank}] {message}", file=sys.stderr, flush=True)
    comm.Abort(2)


def _quiet_build_log() -> None:
    """Keep the C compiler's INFO lines off the console. The first use of a form compiles it
    (FFCx, then cffi through setuptools, which logs "running build_ext" and every gcc command
    line to the root logger at INFO); console handlers of the root logger (the one ffcx installs
    at import, made here first if there is none) print WARNING and above only."""
    import logging

    root = logging.getLogger()
    if not root.handlers:
        logging.basicConfig()  # the handler ffcx's import would install (a no-op there then)
    for h in root.handlers:
        if type(h) is logging.StreamHandler:  # not a test runner's capturing subclass
            h.setLevel(logging.WARNING)


def main(argv: list[str] | None = None) -> int:
    _quiet_build_log()
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except HandFEError as exc:
        _report_error(f"handfe {args.command}: error: {exc}")
        return 2
    except KeyboardInterrupt:
        print(f"handfe {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
