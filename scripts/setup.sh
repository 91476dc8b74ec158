#!/usr/bin/env bash
# Set up a fresh machine: system packages for headless rendering (Mesa EGL on CPU) and Chromium (the
# viewer's browser tests), then a virtual environment in .venv with overgrid and every extra. Safe to
# run again: it only adds what is missing.
set -euo pipefail
cd "$(dirname "$0")/.."

system_packages=(libegl1 libegl-mesa0 libgl1-mesa-dri libglx-mesa0 python3-venv python3-pip openssl chromium)
missing=()
if command -v dpkg >/dev/null 2>&1; then
  for pkg in "${system_packages[@]}"; do
    dpkg -s "$pkg" >/dev/null 2>&1 || missing+=("$pkg")
  done
fi
if ((${#missing[@]})); then
  echo "setup: installing system packages: ${missing[*]}"
  sudo_cmd=()
  [ "$(id -u)" -eq 0 ] || sudo_cmd=(sudo)
  "${sudo_cmd[@]}" apt-get update -qq
  DEBIAN_FRONTEND=noninteractive "${sudo_cmd[@]}" apt-get install -y -qq "${missing[@]}"
fi

python_bin=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  echo "setup: creating .venv"
  "$python_bin" -m venv .venv
fi
stamp=.venv/.overgrid-installed
if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ]; then
  echo "setup: installing overgrid[all,ros2,dev] into .venv"
  .venv/bin/python -m pip install -q --upgrade pip
  .venv/bin/python -m pip install -q -e ".[all,ros2,dev]"
  touch "$stamp"
fi
