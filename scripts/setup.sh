#!/usr/bin/env bash
# Installs what FlyTrack needs on a Debian machine: missing apt packages (sudo when not root),
# then a .venv with the pinned Python requirements and the host package in editable mode.
# Idempotent and quiet when nothing is missing; safe to run on every `make`.
set -euo pipefail
cd "$(dirname "$0")/.."

# FLYTRACK_EXTRA_APT: more package lists, for targets outside `make test` (e.g. scripts/apt-packages-arm.txt).
want=$(cat scripts/apt-packages.txt ${FLYTRACK_EXTRA_APT:-} | grep -v '^\s*#' | grep -v '^\s*$' | tr '\n' ' ')
missing=()
for p in $want; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
if [ ${#missing[@]} -gt 0 ]; then
  echo "setup: installing Debian packages: ${missing[*]}"
  SUDO=""
  if [ "$(id -u)" -ne 0 ]; then
    command -v sudo >/dev/null || { echo "setup: need root or sudo to install ${missing[*]}" >&2; exit 1; }
    SUDO="sudo"
  fi
  export DEBIAN_FRONTEND=noninteractive
  $SUDO apt-get update -qq
  $SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}"
fi

PY=${PYTHON:-python3}
reqs=(host/requirements.txt host/requirements-docs.txt)  # runtime and tests; the docs site
extra="${FLYTRACK_EXTRA_REQS:-}"
stamp=".venv/.flytrack-reqs"
nodeps=host/requirements-nodeps.txt  # test oracles whose own dependencies FlyTrack never calls
sum=$(cat "${reqs[@]}" "$nodeps" $extra host/pyproject.toml | sha256sum | cut -d' ' -f1)
if [ ! -x .venv/bin/python ]; then
  echo "setup: creating .venv"
  "$PY" -m venv .venv
fi
if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$sum" ]; then
  echo "setup: installing pinned Python packages into .venv"
  .venv/bin/python -m pip install -q --upgrade pip
  .venv/bin/python -m pip install -q $(printf -- '-r %s ' "${reqs[@]}") ${extra:+-r $extra}
  .venv/bin/python -m pip install -q --no-deps -r "$nodeps"
  if ! .venv/bin/python -m pip install -q --no-deps --no-build-isolation -e host > .venv/install-host.log 2>&1; then
    cat .venv/install-host.log >&2; echo "setup: installing the host package failed" >&2; exit 1
  fi
  echo "$sum" > "$stamp"
fi
