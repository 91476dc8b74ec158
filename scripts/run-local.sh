#!/usr/bin/env bash
# Set up this machine, then run the whole system locally on the built-in simulated scene.
# Extra arguments go to `overgrid up` (e.g. --duration-s 60 --pairs 2 --out out/run1).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
export MUJOCO_GL=egl
exec .venv/bin/overgrid up "$@"
