"""Do 1 and 2 ranks take the same path on the CI pinch? (the numbers of docs/grasp.md, "1 vs
2 ranks", nineteenth session)

Runs the CI-sized pinch of ``tests/test_grasp_run.py`` (coarse, angles, 1 N per digit) on the
ranks of ``mpirun``, then on rank 0 alone with the mesh the cache kept from that run, exactly as
``test_precision_light_grip_one_rank_matches_two_ranks`` does, and prints one CSV row: whether
the runs took the same decisions (the test's decision list), the first difference, both grips
(N) and their relative difference, both wall times (s). A fresh mesh per row: point
``HANDFE_CACHE_DIR`` at an empty folder (gmsh's HXT meshes differ from run to run)::

    for i in 1 2 3 4 5 6 7; do HANDFE_CACHE_DIR=$(mktemp -d) mpirun -n 2 \\
        .venv/bin/python scripts/pinch_rank_agreement.py --label mesh$i; done
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from mpi4py import MPI

# the test module defines the CI pinch and its decision list; reuse them, not a copy
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from test_grasp_run import decisions, first_difference, light_workflow  # noqa: E402

from handfe.grasp import run_workflow  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--label", default="run", help="first CSV column (e.g. the mesh's name)")
    ap.add_argument("--header", action="store_true", help="print the CSV header first")
    args = ap.parse_args()
    comm = MPI.COMM_WORLD
    wf = light_workflow()
    t0 = time.perf_counter()
    many = run_workflow(wf, out_dir=None, progress=False)
    t_many = time.perf_counter() - t0
    if comm.rank != 0:
        return 0
    t0 = time.perf_counter()
    one = run_workflow(wf, out_dir=None, comm=MPI.COMM_SELF, progress=False)
    t_one = time.perf_counter() - t0
    s1, sn = one.summary, many.summary
    diff = first_difference(decisions(s1), decisions(sn))
    g1, gn = s1["grip_force_N"], sn["grip_force_N"]
    if args.header:
        print(f"label,same_decisions,first_difference,grip_1rank_N,grip_{comm.size}ranks_N,"
              f"relative_difference,wall_1rank_s,wall_{comm.size}ranks_s")
    what = "" if diff is None else '"' + diff[1].replace('"', "'") + '"'
    print(f"{args.label},{diff is None},{what},{g1:.10g},{gn:.10g},"
          f"{abs(g1 - gn) / max(abs(gn), 1e-300):.2e},{t_one:.1f},{t_many:.1f}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
