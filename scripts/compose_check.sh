#!/usr/bin/env bash
# There is no Docker engine on CI: validate docker-compose.yml with whichever
# compose client is installed (the setup installs Debian's docker-compose).
set -euo pipefail
cd "$(dirname "$0")/.."
[ -f docker-compose.yml ] || { echo "compose: no docker-compose.yml yet"; exit 0; }
if docker compose version >/dev/null 2>&1; then
  docker compose --env-file .env.example -f docker-compose.yml config -q
else
  docker-compose --env-file .env.example -f docker-compose.yml config -q
fi
echo "compose: docker-compose.yml is valid"
