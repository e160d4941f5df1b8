"""What a reader that stalls loses: reliable BLOCK messages through a router to a subscriber
whose callback sleeps (a service whose worker stalls, its inbox full), with Zenoh's own 5 s
before a blocked link is closed next to scanflow's `SCANFLOW_ZENOH_BLOCK_CLOSE_S` (60 s).

    python -m bench.link_stall [--stall-s 7] [--messages 20000] [--drain-s 10] [--json]

Every session is opened by `services.common.zsession.open_session`, as the services open
theirs; only `block_close_s` differs between the two runs.
"""

from __future__ import annotations

import argparse
import json
import threading
import time
from typing import Any

import zenoh
from scanflow.config import ZenohSettings

from services.common.launch import free_port
from services.common.zsession import open_session

ZENOH_DEFAULT_S = 5.0
KEY = "scanflow-bench/stall"


def run(
    block_close_s: float, stall_s: float, messages: int, size: int, drain_s: float = 10.0
) -> dict[str, Any]:
    """Publish `messages` of `size` bytes as fast as the link takes them; the reader sleeps
    `stall_s` on its first. How many came, and how long the writer was held back.

    The count is read when the last message has come, or `drain_s` past the stall when it never
    does (its link was closed): enough for the reader to drain what it had queued.
    """
    endpoint = f"tcp/127.0.0.1:{free_port()}"

    def settings(**fields: Any) -> ZenohSettings:
        return ZenohSettings(block_close_s=block_close_s, **fields)

    router = open_session(settings(mode="router", listen=[endpoint], connect=[]))
    reader = open_session(settings(connect=[endpoint]))
    writer = open_session(settings(connect=[endpoint]))
    got: list[int] = []
    last = threading.Event()

    def on_sample(sample: zenoh.Sample) -> None:
        got.append(int(sample.payload.to_bytes()[:8]))
        if len(got) == 1:
            time.sleep(stall_s)
        if got[-1] == messages - 1:
            last.set()

    try:
        subscriber = reader.declare_subscriber(KEY, on_sample)
        publisher = writer.declare_publisher(
            KEY, congestion_control=zenoh.CongestionControl.BLOCK,
            reliability=zenoh.Reliability.RELIABLE,
        )
        time.sleep(0.5)
        t0 = time.perf_counter()
        for i in range(messages):
            publisher.put(f"{i:08d}".encode() + bytes(size - 8))
        publish_s = time.perf_counter() - t0
        last.wait(stall_s + drain_s)
        subscriber.undeclare()
        publisher.undeclare()
    finally:
        for session in (writer, reader, router):
            session.close()
    return {
        "block_close_s": block_close_s,
        "received": len(set(got)),
        "lost": messages - len(set(got)),
        "in_order": got == sorted(got),
        "writer_held_s": round(publish_s, 2),
    }


def main() -> None:
    """Run the stall with Zenoh's default block_close_s and with scanflow's; print both runs."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--stall-s", type=float, default=7.0)
    parser.add_argument("--messages", type=int, default=20_000)
    parser.add_argument("--size", type=int, default=8_000, help="bytes per message")
    parser.add_argument("--drain-s", type=float, default=10.0,
                        help="how long past the stall to wait for a last message that may be lost")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    results = [
        run(close_s, args.stall_s, args.messages, args.size, args.drain_s)
        for close_s in (ZENOH_DEFAULT_S, ZenohSettings().block_close_s)
    ]
    report = {"stall_s": args.stall_s, "messages": args.messages, "size": args.size,
              "runs": results}
    if args.json:
        print(json.dumps(report, indent=2))
        return
    print(f"reader stalls {args.stall_s} s; {args.messages} messages of {args.size} B")
    for r in results:
        print(f"  block_close_s {r['block_close_s']:>5}: received {r['received']}, "
              f"lost {r['lost']}, in order {r['in_order']}, writer held {r['writer_held_s']} s")


if __name__ == "__main__":
    main()
