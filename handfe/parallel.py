"""MPI conveniences: rank-0 printing and scalar reductions. Every solve runs under
``mpirun -n N`` and gives the 1-rank answer; only rank 0 prints and writes files."""

from __future__ import annotations

import sys
from typing import Any

from mpi4py import MPI


def is_root(comm: MPI.Comm = MPI.COMM_WORLD) -> bool:
    return comm.rank == 0


def rprint(*args: Any, comm: MPI.Comm = MPI.COMM_WORLD, file=None, **kwargs: Any) -> None:
    """print() on rank 0 only (flushes, so progress shows under mpirun)."""
    if comm.rank == 0:
        print(*args, file=file or sys.stdout, flush=True, **kwargs)


def allsum(value: float, comm: MPI.Comm) -> float:
    return comm.allreduce(float(value), op=MPI.SUM)


def allmax(value: float, comm: MPI.Comm) -> float:
    return comm.allreduce(float(value), op=MPI.MAX)


def allmin(value: float, comm: MPI.Comm) -> float:
    return comm.allreduce(float(value), op=MPI.MIN)
