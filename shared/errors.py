"""The project's error types, shared by every service.

Low layers raise; the service loop decides (log, count, take the fallback). Decoding is the trust
boundary, so everything wrong with a payload becomes one `ProtocolError` naming the key or schema
and what was wrong.
"""

from __future__ import annotations


class DoveseiError(Exception):
    """Base of every error this project raises on purpose."""


class ProtocolError(DoveseiError, ValueError):
    """A payload that must not reach an algorithm: undecodable, unknown, malformed or oversized."""

    def __init__(self, what: str, problem: str) -> None:
        # `what` names the key expression or schema, `problem` says what was wrong with it.
        super().__init__(f"{what}: {problem}")
        self.what = what
        self.problem = problem


class ConfigError(DoveseiError, ValueError):
    """A bad configuration value, flag or file."""
