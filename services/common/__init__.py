"""The service shell every scanflow service is built on (see shell.py)."""

from services.common.counters import Counters, SeqTracker
from services.common.inbox import Inbox
from services.common.process import configure_logging, init_process
from services.common.shell import ServiceShell, rss_bytes
from services.common.zsession import open_session, zenoh_config

__all__ = [
    "Counters",
    "Inbox",
    "SeqTracker",
    "ServiceShell",
    "configure_logging",
    "init_process",
    "open_session",
    "rss_bytes",
    "zenoh_config",
]
