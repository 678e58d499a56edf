#!/usr/bin/env bash
# Installs the Debian packages HandFE needs, only when something is missing (seconds otherwise).
#   python3-dolfinx  FEniCSx 0.5.2 with PETSc 3.18, petsc4py, mpi4py, ufl (for /usr/bin/python3)
#   python3-gmsh     gmsh Python API for meshing
#   python3-venv     to make the project's .venv
#   libopenblas0     MUMPS on OpenBLAS is 3-5x faster than on the reference BLAS
#   mpi-default-bin  mpirun
set -euo pipefail
PKGS=(python3-dolfinx python3-gmsh python3-venv libopenblas0 mpi-default-bin)

missing=()
for p in "${PKGS[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
if [ ${#missing[@]} -eq 0 ] && /usr/bin/python3 -c "import dolfinx, gmsh" 2>/dev/null; then
  exit 0
fi
if [ ${#missing[@]} -eq 0 ]; then missing=("${PKGS[@]}"); fi

if ! command -v apt-get >/dev/null 2>&1; then
  cat >&2 <<MSG
handfe setup: this machine has no apt-get, so the system packages cannot be installed for you.
Install these yourself (names are Debian 12 / Ubuntu packages; elsewhere use their equivalents):
  FEniCSx dolfinx 0.5.x with PETSc and MUMPS, petsc4py, mpi4py  (Debian: python3-dolfinx)
  the gmsh Python API                                          (Debian: python3-gmsh)
  an MPI launcher (mpirun) and OpenBLAS                        (Debian: mpi-default-bin libopenblas0)
for /usr/bin/python3 (3.11), then run make again.
Missing here: ${missing[*]}
MSG
  exit 1
fi

SUDO=""
if [ "$(id -u)" -ne 0 ]; then
  if command -v sudo >/dev/null 2>&1; then SUDO="sudo"; else
    echo "handfe setup: need root (or sudo) to apt-get install: ${missing[*]}" >&2; exit 1
  fi
fi
echo "handfe setup: installing Debian packages: ${missing[*]}"
$SUDO apt-get update -q
DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -q --no-install-recommends "${missing[@]}"
/usr/bin/python3 -c "import dolfinx, gmsh" || {
  echo "handfe setup: packages installed but 'import dolfinx, gmsh' still fails for /usr/bin/python3" >&2; exit 1; }
