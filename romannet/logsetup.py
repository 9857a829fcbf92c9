"""Logging set-up for the command-line entry points (library code only calls logging.getLogger)."""

from __future__ import annotations

import logging
import os


def setup_logging(level: str | None = None) -> None:
    """Configure the root logger once: level from the argument, else $ROMANNET_LOG_LEVEL, else INFO."""
    name = (level or os.environ.get("ROMANNET_LOG_LEVEL") or "INFO").upper()
    numeric = getattr(logging, name, None)
    if not isinstance(numeric, int):
        raise ValueError(f"log level {name!r} is invalid: use DEBUG, INFO, WARNING or ERROR")
    logging.basicConfig(level=numeric, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
