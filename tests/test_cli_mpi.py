"""The command line under ``mpirun -n 2``: an input error is printed once per job, not once per
rank; an error raised on one rank only is printed with that rank and ends the job."""

import os
import shutil
import subprocess
import sys
import textwrap

import pytest

MPIRUN = shutil.which("mpirun")
pytestmark = pytest.mark.skipif(MPIRUN is None, reason="needs mpirun")


def _mpirun(args: list[str], timeout: float = 120.0) -> subprocess.CompletedProcess:
    root = ["--allow-run-as-root"] if os.geteuid() == 0 else []
    env = {k: v for k, v in os.environ.items()
           if not k.startswith(("OMPI_", "PMI_", "PMIX_"))}  # not the outer launch's rank
    return subprocess.run([MPIRUN, *root, "-n", "2", sys.executable, *args], env=env,
                          capture_output=True, text=True, timeout=timeout)


def test_collective_input_error_printed_once():
    """Both ranks reject the plate angle: one error line, exit code 2 (mpirun passes it on)."""
    p = _mpirun(["-m", "handfe.cli", "fingertip", "--angle", "120", "--force", "4",
                 "--out", os.devnull])
    lines = [ln for ln in p.stderr.splitlines() if "error:" in ln]
    assert p.returncode != 0
    assert len(lines) == 1, p.stderr
    assert "120" in lines[0] and "0..90" in lines[0]


def test_rank_local_error_named_and_aborts():
    """An error on rank 1 alone (rank 0 goes on to a collective call) is printed with the
    rank and the job ends with a non-zero code instead of hanging."""
    code = textwrap.dedent("""
        from mpi4py import MPI
        from handfe.cli import _report_error
        if MPI.COMM_WORLD.rank == 1:
            _report_error("handfe test: error: only here", grace_s=0.5)
        MPI.COMM_WORLD.allreduce(1)
    """)
    p = _mpirun(["-c", code], timeout=60.0)
    assert p.returncode != 0
    assert "[rank 1] handfe test: error: only here" in p.stderr
