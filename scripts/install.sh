#!/usr/bin/env bash
# One-command set-up on Debian/Ubuntu: system packages, a virtual environment in .venv,
# PyTorch (torch==2.13.0: the build your pip index serves), then geofeat with all its extras (docs included). Run from the repository root:
#   bash scripts/install.sh
# Set GEOFEAT_TORCH to another torch requirement, and PIP_INDEX_URL / PIP_EXTRA_INDEX_URL to the index
# that serves the build you want (docs/install.md).
set -euo pipefail
cd "$(dirname "$0")/.."

SUDO=""
if [ "$(id -u)" -ne 0 ]; then SUDO="sudo"; fi
if command -v apt-get >/dev/null 2>&1; then
    $SUDO apt-get update -qq
    # python3-venv for the environment; EGL for the optional pyrender backend ([gl] extra);
    # SuiteSparse for CHOLMOD, the eigensolver's optional faster factorisation (below).
    $SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends \
        python3-venv libegl1 libgl1 libsuitesparse-dev >/dev/null
fi

PYTHON="${PYTHON:-python3}"
"$PYTHON" -m venv .venv
.venv/bin/python -m pip install -q --upgrade pip
# torch first, then keep it pinned: an unpinned torch elsewhere would pull CUDA packages.
.venv/bin/python -m pip install -q "${GEOFEAT_TORCH:-torch==2.13.0}"
.venv/bin/python -m pip freeze | grep -i '^torch==' > .venv/constraints.txt
.venv/bin/python -m pip install -q -c .venv/constraints.txt -e ".[dino,train,gl,bench,test,docs]"
# Optional: CHOLMOD through scikit-sparse (0.4.16 builds against the SuiteSparse 5 of Debian 12,
# later releases need SuiteSparse 7). Without it the eigensolver factorises with SuperLU.
if ! .venv/bin/python -m pip install -q -c .venv/constraints.txt "scikit-sparse==0.4.16" 2>/dev/null \
    && ! .venv/bin/python -m pip install -q -c .venv/constraints.txt scikit-sparse 2>/dev/null; then
    echo "scikit-sparse (CHOLMOD) not installed: the Laplacian eigensolver uses SuperLU (slower, same results)"
fi
.venv/bin/python -c "import geofeat; print('geofeat', geofeat.__version__, 'installed in .venv')"
