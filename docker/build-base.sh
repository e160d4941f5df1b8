#!/usr/bin/env bash
# Build the local base image scanflow-base:bookworm from Debian packages (no registry needed):
# debootstrap a minimal bookworm with python3 + venv, then `docker import` the tree.
# Idempotent: does nothing when the image exists, unless --force is given.
#
#   docker/build-base.sh [--force]
# Environment: SCANFLOW_BASE_IMAGE (default scanflow-base:bookworm),
#              DEBIAN_MIRROR (default: the first Debian mirror apt uses here, else deb.debian.org).
set -euo pipefail

image="${SCANFLOW_BASE_IMAGE:-scanflow-base:bookworm}"
force=0
for arg in "$@"; do
  case "$arg" in
    --force) force=1 ;;
    -h|--help) sed -n '2,9p' "$0"; exit 0 ;;
    *) echo "build-base.sh: unknown argument '$arg' (expected --force)" >&2; exit 2 ;;
  esac
done

if [ "$force" -eq 0 ] && docker image inspect "$image" >/dev/null 2>&1; then
  echo "build-base.sh: $image exists, skipping (use --force to rebuild)"
  exit 0
fi

sudo_cmd=()
if [ "$(id -u)" -ne 0 ]; then
  sudo_cmd=(sudo)
fi

if ! command -v debootstrap >/dev/null 2>&1 && [ ! -x /usr/sbin/debootstrap ]; then
  echo "build-base.sh: installing debootstrap"
  "${sudo_cmd[@]}" apt-get install -y --no-install-recommends debootstrap >/dev/null \
    || { "${sudo_cmd[@]}" apt-get update >/dev/null && \
         "${sudo_cmd[@]}" apt-get install -y --no-install-recommends debootstrap >/dev/null; }
fi
debootstrap_bin="$(command -v debootstrap || echo /usr/sbin/debootstrap)"

default_mirror() {
  # The mirror apt already uses on this host (deb822 "URIs:" or one-line "deb" form).
  local uri
  uri="$(grep -rhoE '^(URIs:[[:space:]]*|deb[[:space:]]+(\[[^]]*\][[:space:]]+)?)[a-z]+://[^[:space:]]+/debian/?([[:space:]]|$)' \
           /etc/apt/sources.list /etc/apt/sources.list.d/ 2>/dev/null \
         | grep -oE '[a-z]+://[^[:space:]]+' | head -n1 || true)"
  echo "${uri:-http://deb.debian.org/debian}"
}
mirror="${DEBIAN_MIRROR:-$(default_mirror)}"

rootfs="$(mktemp -d "${TMPDIR:-/tmp}/scanflow-rootfs.XXXXXX")"
cleanup() { "${sudo_cmd[@]}" rm -rf "$rootfs"; }
trap cleanup EXIT

echo "build-base.sh: debootstrap bookworm from $mirror into $rootfs"
"${sudo_cmd[@]}" "$debootstrap_bin" --variant=minbase --include=python3,python3-venv \
  bookworm "$rootfs" "$mirror" >"$rootfs.log" 2>&1 \
  || { tail -n 30 "$rootfs.log" >&2; rm -f "$rootfs.log"; exit 1; }
rm -f "$rootfs.log"

# Nothing in the image needs the package caches, docs or man pages.
"${sudo_cmd[@]}" rm -rf "$rootfs"/var/cache/apt/archives/*.deb "$rootfs"/var/lib/apt/lists/* \
  "$rootfs"/usr/share/doc/* "$rootfs"/usr/share/man/* "$rootfs"/usr/share/info/*

"${sudo_cmd[@]}" tar --numeric-owner -C "$rootfs" -c . \
  | docker import \
      --change 'ENV LANG=C.UTF-8' \
      --change 'ENV PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin' \
      --change 'CMD ["python3"]' \
      --message "debootstrap --variant=minbase --include=python3,python3-venv bookworm" \
      - "$image" >/dev/null
echo "build-base.sh: built $image ($(docker image inspect -f '{{.Size}}' "$image") bytes)"
