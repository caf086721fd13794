#!/usr/bin/env bash
# Idempotent setup for a fresh Debian/Ubuntu machine: system packages (when root),
# the Python virtual environment and the frontend's npm packages. Each step is
# skipped when what it installs is already there and unchanged.
set -euo pipefail
cd "$(dirname "$0")/.."

log() { printf '\033[1m[setup]\033[0m %s\n' "$*"; }

# --- Debian packages -------------------------------------------------------
apt_wanted=()
command -v redis-server >/dev/null || apt_wanted+=(redis-server)
[ -x /usr/bin/chromium ] || apt_wanted+=(chromium)
dpkg -s libusb-1.0-0 >/dev/null 2>&1 || apt_wanted+=(libusb-1.0-0)   # open3d imports it
dpkg -s libgl1 >/dev/null 2>&1 || apt_wanted+=(libgl1 libgomp1)        # open3d's shared libs
command -v docker-compose >/dev/null || docker compose version >/dev/null 2>&1 || apt_wanted+=(docker-compose)
command -v psql >/dev/null || apt_wanted+=(postgresql-client)
# Dr.Jit's LLVM backend for Mitsuba's llvm_ad_rgb variant (LLVM 15 cannot compile its
# kernels); without it worker.simulate.mitsuba falls back to the slower scalar_rgb.
dpkg -s libllvm19 >/dev/null 2>&1 || apt_wanted+=(libllvm19)
if [ ${#apt_wanted[@]} -gt 0 ]; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
    log "installing Debian packages (apt-get): ${apt_wanted[*]}"
    export DEBIAN_FRONTEND=noninteractive
    apt-get update -qq
    apt-get install -y -qq --no-install-recommends "${apt_wanted[@]}" >/dev/null
  else
    log "WARNING: not root; please install: ${apt_wanted[*]}"
  fi
fi

# --- Python -----------------------------------------------------------------
PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  log "creating .venv"
  "$PY" -m venv .venv
fi
stamp=.venv/.installed-$(sha256sum pyproject.toml | cut -c1-16)
if [ ! -f "$stamp" ]; then
  log "installing Python packages into .venv (pyproject.toml changed or first run):"
  # Say what: every pinned requirement of pyproject.toml, by group.
  .venv/bin/python - <<'PYEOF'
import tomllib

project = tomllib.load(open("pyproject.toml", "rb"))["project"]
groups = {"core": project.get("dependencies", []), **project.get("optional-dependencies", {})}
for name, reqs in groups.items():
    named = [r for r in reqs if not r.startswith(project["name"])]
    if named:
        print(f"          {name}: {', '.join(named)}")
PYEOF
  # This machine's pip.conf names optional local mirrors that may be absent: hide that noise only.
  .venv/bin/python -m pip install -q --disable-pip-version-check --upgrade "pip==25.3" \
    2> >(grep -v "is neither a file nor a directory" >&2)
  .venv/bin/python -m pip install -q --disable-pip-version-check -e ".[all]" \
    2> >(grep -v "is neither a file nor a directory" >&2)
  # IIIF manifest validation in tests; --no-deps: its Pillow<=12 cap would undo our pin.
  .venv/bin/python -m pip install -q --disable-pip-version-check --no-deps "iiif-prezi3==3.1.1" \
    2> >(grep -v "is neither a file nor a directory" >&2)
  rm -f .venv/.installed-*
  touch "$stamp"
fi

# --- Node (frontend) ----------------------------------------------------------
if [ -f frontend/package.json ]; then
  lockhash=$(cat frontend/package.json frontend/package-lock.json 2>/dev/null | sha256sum | cut -c1-16)
  if [ ! -f "frontend/node_modules/.installed-$lockhash" ]; then
    log "installing npm packages into frontend/node_modules:"
    .venv/bin/python -c 'import json; p = json.load(open("frontend/package.json")); [print(f"          {k}: " + ", ".join(f"{n}@{v}" for n, v in p.get(k, {}).items())) for k in ("dependencies", "devDependencies") if p.get(k)]'
    if [ -f frontend/package-lock.json ]; then
      (cd frontend && npm ci --no-audit --no-fund --loglevel=error >/dev/null)
    else
      (cd frontend && npm install --no-audit --no-fund --loglevel=error >/dev/null)
    fi
    rm -f frontend/node_modules/.installed-*
    touch "frontend/node_modules/.installed-$lockhash"
  fi
  if [ ! -f frontend/dist/index.html ] || [ -n "$(find frontend/src frontend/index.html frontend/*.html frontend/vite.config.js -newer frontend/dist/index.html 2>/dev/null | head -1)" ]; then
    log "building the frontend"
    (cd frontend && npm run --silent build >/dev/null)
  fi
fi
log "ready"
