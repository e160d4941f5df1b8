#!/usr/bin/env bash
# Run the test suite; a run that collects no test is a failure, not a silent pass.
set -u
py="${1:-python3}"
bash "$(dirname "$0")/system-deps.sh"
"$py" -m pytest "${@:2}"
rc=$?
if [ "$rc" -eq 5 ]; then
  echo "pytest collected no tests: treating as a failure" >&2
  exit 1
fi
exit "$rc"
