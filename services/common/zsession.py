"""Open a Zenoh session from `ZenohSettings`: the one place services turn settings into config;
and sort a query's replies into answers and errors."""

from __future__ import annotations

import json
from collections.abc import Iterable

import zenoh
from scanflow.config import ZenohSettings


def zenoh_config(settings: ZenohSettings) -> zenoh.Config:
    """A `zenoh.Config` with mode, connect/listen endpoints, scouting and how long a blocked
    link may wait (`block_close_s`) from `settings`."""
    config = zenoh.Config()
    config.insert_json5("mode", json.dumps(settings.mode))
    if settings.connect:
        config.insert_json5("connect/endpoints", json.dumps(list(settings.connect)))
    if settings.listen:
        config.insert_json5("listen/endpoints", json.dumps(list(settings.listen)))
    config.insert_json5("scouting/multicast/enabled", json.dumps(settings.multicast_scouting))
    config.insert_json5(
        "transport/link/tx/queue/congestion_control/block/wait_before_close",
        json.dumps(round(settings.block_close_s * 1e6)),
    )
    return config


def open_session(settings: ZenohSettings) -> zenoh.Session:
    """Open a session; raises with the endpoints named when the router cannot be reached."""
    try:
        return zenoh.open(zenoh_config(settings))
    except zenoh.ZError as exc:
        raise RuntimeError(
            f"cannot open a Zenoh session (mode={settings.mode!r}, "
            f"connect={settings.connect!r}, listen={settings.listen!r}): {exc}"
        ) from exc


def sorted_replies(replies: Iterable[zenoh.Reply]) -> tuple[list[tuple[str, bytes]], list[str]]:
    """A query's replies, in order: (key, payload) of each answer, and the text of each error
    reply (a queryable that refused or failed; Zenoh's own for one that did not finish)."""
    answers: list[tuple[str, bytes]] = []
    errors: list[str] = []
    for reply in replies:
        result = reply.result  # a Sample, or the ReplyError of a failed reply
        if isinstance(result, zenoh.ReplyError):
            # Any queryable on the key may answer: text that is not UTF-8 is still read.
            errors.append(result.payload.to_bytes().decode(errors="replace"))
        else:
            answers.append((str(result.key_expr), result.payload.to_bytes()))
    return answers, errors
