#!/usr/bin/env bash
# Debian packages some tests need beyond Python: chromium (the web page test, driven by
# Playwright) and debootstrap (the local base image for the docker-compose tests).
# Installs what is missing when running as root with apt-get; otherwise says what is missing
# and leaves the tests that need it to skip with a loud reason.
set -u
missing=()
command -v chromium >/dev/null 2>&1 || missing+=(chromium)
command -v debootstrap >/dev/null 2>&1 || missing+=(debootstrap)
[ ${#missing[@]} -eq 0 ] && exit 0
if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
  echo "system-deps: installing ${missing[*]}" >&2
  export DEBIAN_FRONTEND=noninteractive
  if apt-get update -qq >/dev/null && apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null; then
    exit 0
  fi
  echo "system-deps: apt-get could not install ${missing[*]}" >&2
else
  echo "system-deps: missing ${missing[*]} (install with: sudo apt-get install ${missing[*]})" >&2
fi
exit 0
