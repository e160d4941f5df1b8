#!/usr/bin/env bash
# Run the test suite; a run that collects no test is a failure, not a silent pass.
#   tools/run-tests.sh PYTHON [PYTEST ARGS...]
# Without pytest arguments (`make test`, CI) the container tests (-m docker: minutes spent
# mostly waiting on image builds, Zenoh leases and health checks) and the tests marked
# second_lane (long service runs, chosen so that the two processes end about together) run in a
# second pytest process alongside the rest, on the otherwise idle second core (the container
# tests first: tests/docker/conftest.py says why); their report follows the main one and
# either run failing fails the whole. With arguments: one pytest run with exactly those.
set -u
py="${1:-python3}"
bash "$(dirname "$0")/system-deps.sh"

# pytest's exit code, except that "no tests collected" (5) is a failure.
checked() {
  if [ "$1" -eq 5 ]; then
    echo "pytest collected no tests ($2): treating as a failure" >&2
    return 1
  fi
  return "$1"
}

if [ $# -gt 1 ]; then
  "$py" -m pytest "${@:2}"
  checked $? "pytest ${*:2}"
  exit
fi

side="docker or second_lane"
log="$(mktemp)"
trap 'rm -f "$log"' EXIT
# A background job starts with SIGINT ignored: restore it, so that Ctrl-C ends that run too,
# through pytest's teardown (its compose projects taken down); the script then waits for it.
"$py" -c 'import signal, sys, pytest
signal.signal(signal.SIGINT, signal.default_int_handler)
sys.exit(pytest.main(sys.argv[1:]))' -m "$side" >"$log" 2>&1 &
side_pid=$!
trap ':' INT
"$py" -m pytest -m "not ($side)"
main_rc=$?
echo "==== waiting for the second process (pytest -m '$side', started alongside) ===="
while :; do  # `wait` returns early when Ctrl-C comes: wait again while the run goes on
  wait "$side_pid"
  side_rc=$?
  kill -0 "$side_pid" 2>/dev/null || break
done
cat "$log"
checked "$main_rc" "-m 'not ($side)'"
main_rc=$?
checked "$side_rc" "-m '$side'"
side_rc=$?
echo "==== exit codes: -m 'not ($side)' $main_rc, -m '$side' $side_rc ===="
[ "$main_rc" -eq 0 ] && [ "$side_rc" -eq 0 ]
