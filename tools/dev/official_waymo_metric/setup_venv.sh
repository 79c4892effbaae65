#!/usr/bin/env bash
# Build the isolated virtual environment holding the official Waymo metric op.
#
# Usage: tools/dev/official_waymo_metric/setup_venv.sh [VENV_DIR]
# Default VENV_DIR: <repo>/.cache/waymo_official_venv (gitignored). Needs python3.11 and PyPI access;
# the download is ~600 MB (tensorflow 2.13).
set -euo pipefail
HERE="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
REPO="$(cd "${HERE}/../../.." && pwd)"
VENV="${1:-${WAYMO_OFFICIAL_VENV:-${REPO}/.cache/waymo_official_venv}}"
PY="${PYTHON311:-python3.11}"
"${PY}" -m venv "${VENV}"
"${VENV}/bin/python" -m pip install --upgrade pip
"${VENV}/bin/python" -m pip install -r "${HERE}/requirements.txt"
"${VENV}/bin/python" -c "from waymo_open_dataset.metrics.ops import py_metrics_ops; print('official op OK')"
echo "venv ready: ${VENV}"
