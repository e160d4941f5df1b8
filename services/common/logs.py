"""One logging format for every service process."""

from __future__ import annotations

import logging


def configure_logging(level: str) -> None:
    """Timestamped, service-named lines on stderr."""
    logging.basicConfig(
        level=level, format="%(asctime)s %(levelname)s %(name)s: %(message)s", force=True
    )
