"""Post-install sanity check: FEniCSx imports, numpy is 1.x, and which BLAS MUMPS will use."""

import os
import sys

import numpy as np

problems = []
if int(np.__version__.split(".")[0]) >= 2:
    problems.append(f"numpy {np.__version__} in the venv; Debian's FEniCSx needs numpy 1.x")
try:
    import dolfinx
    import gmsh  # noqa: F401
    from petsc4py import PETSc  # noqa: F401
except Exception as exc:  # noqa: BLE001
    problems.append(f"FEniCSx stack does not import: {exc}")
else:
    if not dolfinx.__version__.startswith("0.5."):
        print(f"note: dolfinx {dolfinx.__version__}; HandFE is developed on 0.5.2", file=sys.stderr)

blas = "unknown"
for link in ("/etc/alternatives/libblas.so.3-x86_64-linux-gnu",
             "/etc/alternatives/libblas.so.3-aarch64-linux-gnu"):
    if os.path.exists(link):
        blas = os.path.realpath(link)
if "openblas" not in blas:
    print(f"warning: BLAS in use is {blas}; MUMPS is 3-5x slower than with OpenBLAS "
          "(apt-get install libopenblas0)", file=sys.stderr)
if problems:
    print("handfe setup: " + "; ".join(problems), file=sys.stderr)
    sys.exit(1)
print(f"handfe setup: dolfinx {dolfinx.__version__}, numpy {np.__version__}, BLAS {blas}")
