#!/usr/bin/env bash
# Install everything topseg needs into .venv, Debian packages included.
# Idempotent and non-interactive: safe to rerun, asks nothing (CI runs it as root with no stdin).
set -euo pipefail
cd "$(dirname "$0")/.."

APT_PACKAGES=(libfreenect-dev libfreenect-bin libopenni2-dev libopenni2-0 python3-venv gcc)
PYTHON=${PYTHON:-python3}

missing=()
for pkg in "${APT_PACKAGES[@]}"; do
    dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "install ok installed" || missing+=("$pkg")
done
if [ ${#missing[@]} -gt 0 ]; then
    echo "install: Debian packages: ${missing[*]}"
    SUDO=""
    [ "$(id -u)" -ne 0 ] && SUDO="sudo -n"
    export DEBIAN_FRONTEND=noninteractive
    $SUDO apt-get update -qq
    $SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}" </dev/null
fi

if [ ! -x .venv/bin/python ]; then
    echo "install: creating .venv with $($PYTHON --version)"
    "$PYTHON" -m venv .venv
fi
.venv/bin/python -m pip install -q --disable-pip-version-check --upgrade pip "setuptools>=77" wheel Cython
echo "install: topseg and its Python dependencies into .venv"
# every extra: the live services, synthesis and training, each sensor SDK, the tests
.venv/bin/python -m pip install -q --disable-pip-version-check -e ".[all,kinect,test]"
.venv/bin/topseg --version
# numba's kernels compiled into its cache now, a process per core (~2 min on 2 cores), not on a
# worker's first start or spread over the test suite's first runs
.venv/bin/topseg compile
