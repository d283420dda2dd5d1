"""Warnings a command gives once per process, as one log line (no Python source line)."""

from __future__ import annotations

import logging

_issued: set[str] = set()


def warn_once(logger: logging.Logger, topic: str, message: str, *args) -> bool:
    """Log ``message % args`` as a warning the first time ``topic`` comes up in this process.

    Returns whether it was logged; later calls with the same topic log at debug level only.
    """
    if topic in _issued:
        logger.debug(message, *args)
        return False
    _issued.add(topic)
    logger.warning(message, *args)
    return True


def reset_warnings() -> None:
    """Forget which topics were warned about (tests, or a long-lived process starting a new job)."""
    _issued.clear()
