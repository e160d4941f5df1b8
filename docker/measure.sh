#!/usr/bin/env bash
# Measure the compose deployment: image size, time from `up` to every service healthy (the
# image already built: a warm build cache), and memory per container after ingest finished.
#   docker/measure.sh [runs]        (default 3 runs; prints one line per figure)
# Uses its own compose project (scanflow-measure) on a free port and removes it (down -v).
set -euo pipefail
repo="$(cd "$(dirname "$0")/.." && pwd)"
runs="${1:-3}"
image="${SCANFLOW_IMAGE:-scanflow:latest}"
if docker compose version >/dev/null 2>&1; then compose=(docker compose); else compose=(docker-compose); fi
project=scanflow-measure
port="$(python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1",0)); print(s.getsockname()[1])')"
export SCANFLOW_IMAGE="$image" SCANFLOW_GATEWAY_PUBLISH="$port" SCANFLOW_INGEST_RATE=0 \
       SCANFLOW_INGEST_SIM_DURATION_S="${SCANFLOW_INGEST_SIM_DURATION_S:-30}"
dc() { "${compose[@]}" -p "$project" -f "$repo/docker-compose.yml" "$@"; }
trap 'dc down -v --remove-orphans --timeout 10 >/dev/null 2>&1 || true' EXIT
services=(router deskew matcher mapserver gateway)

docker image inspect "$image" >/dev/null 2>&1 || bash "$repo/docker/build.sh"
echo "image $image: $(docker image inspect -f '{{.Size}}' "$image" | awk '{printf "%.0f MB", $1/1e6}')"

healthy() {
  local s id
  for s in "${services[@]}"; do
    id="$(dc ps -q "$s")"
    [ -n "$id" ] && [ "$(docker inspect -f '{{if .State.Health}}{{.State.Health.Status}}{{end}}' "$id")" = healthy ] || return 1
  done
}

for run in $(seq 1 "$runs"); do
  dc down -v --remove-orphans --timeout 10 >/dev/null 2>&1 || true
  t0="$(date +%s%N)"
  dc up -d --no-build >/dev/null 2>&1
  until healthy; do
    sleep 0.2
    if [ $(( $(date +%s%N) - t0 )) -gt 300000000000 ]; then echo "not healthy after 300 s" >&2; exit 1; fi
  done
  ms=$(( ($(date +%s%N) - t0) / 1000000 ))
  printf 'run %d: up -> all healthy in %d.%d s\n' "$run" $((ms / 1000)) $((ms % 1000 / 100))
done

# Memory after the simulated run went through (ingest exits when it is done).
ingest="$(dc ps -q ingest)"
timeout 300 docker wait "$ingest" >/dev/null
echo "memory per container after a ${SCANFLOW_INGEST_SIM_DURATION_S} s simulated run:"
for s in "${services[@]}"; do
  docker stats --no-stream --format "  $s: {{.MemUsage}} (cpu {{.CPUPerc}})" "$(dc ps -q "$s")"
done
