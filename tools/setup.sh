#!/usr/bin/env bash
# Set up clrefract on a fresh machine: an OpenCL CPU driver and a virtual environment in .venv.
# Idempotent; safe to run before every command.
#
#   bash tools/setup.sh                 Debian's PoCL where apt works (else pip's drivers), .venv
#   bash tools/setup.sh --pip-only DIR  a venv at DIR with pip's drivers alone and a plain
#                                       (non-editable) install, as a user without root has it
set -euo pipefail
cd "$(dirname "$0")/.."

if [ "${1:-}" = "--pip-only" ]; then
  venv="${2:?usage: setup.sh --pip-only DIR}"
  [ -x "$venv/bin/python" ] || python3 -m venv "$venv"
  "$venv/bin/python" -m pip install -q --upgrade pip
  # both pip CPU drivers: PoCL, and Intel's runtime for CPUs pip PoCL's LLVM 14 does not know
  mpi=""
  command -v mpiexec >/dev/null 2>&1 && mpi=",mpi"  # mpi4py needs the system's MPI library
  "$venv/bin/python" -m pip install -q ".[test,pocl,cpu$mpi]"
  exit 0
fi

have_icd() { ls /etc/OpenCL/vendors/*.icd >/dev/null 2>&1; }

# Debian's PoCL is faster than the pip wheel (SPEC section 7); use it where apt works.
if ! have_icd && command -v apt-get >/dev/null 2>&1 && [ "$(id -u)" = 0 ]; then
  (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq \
      pocl-opencl-icd ocl-icd-libopencl1 >/dev/null) || echo "setup: apt failed, using pip's drivers"
fi

# MPI for data-parallel fitting and its `mpiexec -n 2` test; optional (the test skips without)
if ! command -v mpiexec >/dev/null 2>&1 && command -v apt-get >/dev/null 2>&1 && [ "$(id -u)" = 0 ]; then
  (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq \
      openmpi-bin libopenmpi-dev >/dev/null) || echo "setup: no MPI from apt; MPI tests will skip"
fi

# Oclgrind, a simulated OpenCL device that reports out-of-bounds and uninitialised reads and
# races (tools/oclgrind_check.py); optional (its test skips without). It adds no ICD file.
if ! command -v oclgrind >/dev/null 2>&1 && command -v apt-get >/dev/null 2>&1 && [ "$(id -u)" = 0 ]; then
  (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq \
      oclgrind >/dev/null) || echo "setup: no oclgrind from apt; its test will skip"
fi

if [ ! -x .venv/bin/python ]; then
  python3 -m venv .venv
fi
extras="test"
have_icd || extras="test,pocl,cpu"
command -v mpiexec >/dev/null 2>&1 && extras="$extras,mpi"
stamp=".venv/.clrefract-installed-$extras-$(sha1sum pyproject.toml | cut -c1-12)"
if [ ! -f "$stamp" ]; then
  .venv/bin/python -m pip install -q --upgrade pip
  .venv/bin/python -m pip install -q -e ".[$extras]"
  touch "$stamp"
fi
