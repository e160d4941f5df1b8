#!/usr/bin/env bash
# Build the scanflow image with no registry access: download manylinux wheels of the runtime
# dependencies (pyproject `dependencies`, not the dev/bench extras) and build the scanflow wheel
# on the host into docker/wheels/, then `docker build` scanflow:latest on a base image.
#
#   docker/build.sh [--base IMAGE] [--tag TAG] [--no-base-build]
# --base IMAGE      base image (default scanflow-base:bookworm, built by build-base.sh when
#                   missing; pass python:3.11-slim-bookworm where a registry is reachable)
# --tag TAG         image tag (default scanflow:latest)
# --no-base-build   never run build-base.sh (the base must exist or be pullable)
# Environment: PYTHON (host interpreter with pip; default .venv/bin/python, else python3),
#              SCANFLOW_WHEEL_STORE (host wheel store; default
#              ~/.cache/scanflow/docker-wheels/cp311-<arch>).
set -euo pipefail

repo="$(cd "$(dirname "$0")/.." && pwd)"
base="${SCANFLOW_BASE_IMAGE:-scanflow-base:bookworm}"
tag="scanflow:latest"
build_base=1
while [ $# -gt 0 ]; do
  case "$1" in
    --base) base="${2:?--base needs an image name}"; shift 2 ;;
    --tag) tag="${2:?--tag needs an image tag}"; shift 2 ;;
    --no-base-build) build_base=0; shift ;;
    -h|--help) sed -n '2,14p' "$0"; exit 0 ;;
    *) echo "build.sh: unknown argument '$1'" >&2; exit 2 ;;
  esac
done

if [ -n "${PYTHON:-}" ]; then py="$PYTHON"
elif [ -x "$repo/.venv/bin/python" ]; then py="$repo/.venv/bin/python"
else py=python3; fi

if [ "$build_base" -eq 1 ] && [ "$base" = "scanflow-base:bookworm" ]; then
  SCANFLOW_BASE_IMAGE="$base" bash "$repo/docker/build-base.sh"
fi

case "$(docker info -f '{{.Architecture}}')" in
  x86_64|amd64) arch=x86_64 ;;
  aarch64|arm64) arch=aarch64 ;;
  *) echo "build.sh: unsupported docker architecture $(docker info -f '{{.Architecture}}')" >&2; exit 1 ;;
esac

deps="$repo/docker/wheels/deps"
app="$repo/docker/wheels/app"
mkdir -p "$deps" "$app"

# 1. Runtime dependency wheels for CPython 3.11 on glibc 2.36 (bookworm), downloaded into a
#    wheel store shared by every checkout on this host (pip keeps no cache here, and a fresh
#    clone would fetch ~140 MB again), then linked into a stable directory of the build context
#    so unchanged dependencies leave the docker layer cache valid.
store="${SCANFLOW_WHEEL_STORE:-${XDG_CACHE_HOME:-$HOME/.cache}/scanflow/docker-wheels/cp311-$arch}"
mkdir -p "$store"
"$py" - "$repo/pyproject.toml" "$deps/requirements.txt" <<'PY'
import sys, tomllib
from pathlib import Path
deps = tomllib.loads(Path(sys.argv[1]).read_text())["project"]["dependencies"]
text = "".join(f"{d}\n" for d in deps)
out = Path(sys.argv[2])
if not out.exists() or out.read_text() != text:
    out.write_text(text)
PY
echo "build.sh: downloading dependency wheels into $store"
log="$(mktemp)"
trap 'rm -f "$log"' EXIT
# pip does not widen a --platform to older glibc tags itself: list every tag bookworm runs.
platforms=()
for minor in $(seq 36 -1 5); do platforms+=(--platform "manylinux_2_${minor}_$arch"); done
for legacy in manylinux2014 manylinux2010 manylinux1; do platforms+=(--platform "${legacy}_$arch"); done
"$py" -m pip download --progress-bar off --disable-pip-version-check \
  --only-binary=:all: --implementation cp --python-version 3.11 "${platforms[@]}" \
  --dest "$store" -r "$deps/requirements.txt" >"$log" 2>&1 \
  || { tail -n 30 "$log" >&2; exit 1; }
# The context holds exactly the resolved wheels (the image installs what the directory holds):
# stale versions dropped, the others hard-linked (copied across file systems) from the store.
mapfile -t keep < <(grep -oE '(Saved|File was already downloaded) [^ ]+\.whl' "$log" \
                      | awk '{print $NF}' | xargs -r -n1 basename | sort -u)
for whl in "$deps"/*.whl; do
  [ -e "$whl" ] || continue
  name="$(basename "$whl")"
  printf '%s\n' "${keep[@]}" | grep -qxF "$name" || { echo "build.sh: removing stale $name"; rm -f "$whl"; }
done
for name in "${keep[@]}"; do
  [ -e "$deps/$name" ] || ln "$store/$name" "$deps/$name" 2>/dev/null || cp "$store/$name" "$deps/$name"
done

# 2. The scanflow wheel, built from the files git knows (tracked and untracked, not ignored)
#    in a clean copy, with fixed timestamps so an unchanged tree gives an identical wheel.
src="$(mktemp -d)"
trap 'rm -f "$log"; rm -rf "$src"' EXIT
if git -C "$repo" rev-parse --is-inside-work-tree >/dev/null 2>&1; then
  # (--ignore-failed-read: files deleted in the work tree but still tracked are skipped)
  (cd "$repo" && git ls-files -z --cached --others --exclude-standard \
     | tar --null -T - --ignore-failed-read -cf - 2>/dev/null) | tar -C "$src" -xf -
else
  tar -C "$repo" --exclude=.venv --exclude=.git --exclude=docker/wheels -cf - . | tar -C "$src" -xf -
fi
rm -f "$app"/*.whl
echo "build.sh: building the scanflow wheel"
SOURCE_DATE_EPOCH=315532800 "$py" -m pip wheel --quiet --disable-pip-version-check --no-deps \
  --wheel-dir "$app" "$src" >"$log" 2>&1 || { tail -n 30 "$log" >&2; exit 1; }

# 3. The image.
echo "build.sh: docker build $tag on $base"
# BuildKit when the buildx plugin exists, else the classic builder (the Dockerfile suits both).
if [ -z "${DOCKER_BUILDKIT:-}" ]; then
  if docker buildx version >/dev/null 2>&1; then export DOCKER_BUILDKIT=1; else export DOCKER_BUILDKIT=0; fi
fi
docker build --build-arg "BASE_IMAGE=$base" \
  -f "$repo/docker/Dockerfile" -t "$tag" "$repo"
