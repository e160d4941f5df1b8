"""Container health check for the scanflow image: exit 0 when this container's service answers.

The service is the argument, else the word after `serve` in the container's command (PID 1).
Zenoh services (router included) must answer their stats query through the Zenoh network, so a
hung worker or a container cut off from the router reports unhealthy; the gateway must answer
200 on its health endpoint. A container that runs no service (e.g. `scanflow version`) is healthy.
It runs every few seconds in every container, so it reads the few SCANFLOW_* variables it needs
itself: scanflow.config and the service shell would import pydantic and numpy (~0.4 s of CPU
per check, measured) for three strings.
"""

from __future__ import annotations

import json
import os
import sys
import urllib.error
import urllib.request
from pathlib import Path

TIMEOUT_S = 5.0


def service_of_pid1(cmdline_path: Path = Path("/proc/1/cmdline")) -> str | None:
    """The `<name>` of `... serve <name>` in PID 1's command line, or None."""
    args = cmdline_path.read_bytes().decode(errors="replace").split("\0")
    if "serve" in args:
        index = args.index("serve") + 1
        if index < len(args) and args[index]:
            return args[index]
    return None


def gateway_ok() -> tuple[bool, str]:
    """The gateway answers 200 on GET /api/v1/health (503 = its own Zenoh session is down)."""
    port = os.environ.get("SCANFLOW_GATEWAY_PORT", "8000")
    url = f"http://127.0.0.1:{port}/api/v1/health"
    try:
        with urllib.request.urlopen(url, timeout=TIMEOUT_S) as response:
            return response.status == 200, f"{url} -> {response.status}"
    except urllib.error.HTTPError as exc:
        return False, f"{url} -> {exc.code}"
    except OSError as exc:
        return False, f"{url}: {exc}"


def env_list(name: str, default: str) -> list[str]:
    """A list variable as scanflow.config reads it: JSON (`["a", "b"]`) or comma-separated."""
    value = os.environ.get(name, default).strip()
    if value.startswith("["):
        return list(json.loads(value))
    return [v.strip() for v in value.split(",") if v.strip()]


def zenoh_service_ok(service: str) -> tuple[bool, str]:
    """The service's stats queryable answers through the router (the router: its own)."""
    import zenoh
    from scanflow import keys

    if service == "router":
        port = env_list("SCANFLOW_ROUTER_LISTEN", "tcp/0.0.0.0:7447")[0].rsplit(":", 1)[-1]
        connect = [f"tcp/127.0.0.1:{port}"]
    else:
        connect = env_list("SCANFLOW_ZENOH_CONNECT", "tcp/127.0.0.1:7447")
    config = zenoh.Config()
    config.insert_json5("mode", '"client"')
    config.insert_json5("connect/endpoints", json.dumps(connect))
    config.insert_json5("scouting/multicast/enabled", "false")
    instance = os.environ.get(f"SCANFLOW_{service.upper()}_INSTANCE", "*")
    key = keys.stats(service, instance, os.environ.get("SCANFLOW_ZENOH_PREFIX", "scanflow"))
    session = zenoh.open(config)
    try:
        replies = list(session.get(key, timeout=TIMEOUT_S))
    finally:
        session.close()
    answered = [r for r in replies if r.ok is not None]
    return bool(answered), f"{key}: {len(answered)} answer(s) of {len(replies)} reply(ies)"


def main(argv: list[str]) -> int:
    service = argv[1] if len(argv) > 1 else service_of_pid1()
    if service is None:
        return 0
    try:
        ok, detail = gateway_ok() if service == "gateway" else zenoh_service_ok(service)
    except Exception as exc:  # any failure to check is "unhealthy", with the reason shown
        ok, detail = False, f"{type(exc).__name__}: {exc}"
    print(f"{service}: {'healthy' if ok else 'UNHEALTHY'} ({detail})")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main(sys.argv))
