"""Typed errors shared by every component, so callers can catch one class per failure kind."""


class RomannetError(Exception):
    """Base class of every error this project raises on purpose."""


class ConfigError(RomannetError, ValueError):
    """A configuration value is wrong; the message names the field, the value and what is allowed."""

    def __init__(self, field: str, value: object, allowed: str):
        self.field = field
        self.value = value
        self.allowed = allowed
        super().__init__(f"config field '{field}' = {value!r} is invalid: {allowed}")


class DecodeError(RomannetError, ValueError):
    """Bytes from the network or from a file are not a valid message (malformed, out of range, non-finite)."""


class RobotError(RomannetError, RuntimeError):
    """A real robot or camera cannot be used: unreachable, not ready, a driver missing, no frame in time."""
