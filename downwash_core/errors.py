"""The project's exceptions: a small hierarchy, so that a caller can catch a bad
configuration or a bad file apart from a bug.

    TestbedError
    ├── ConcurrentUseError (RuntimeError)  a second thread used a simulator while one was in it
    ├── ConfigError (ValueError)     an argument, option or configuration is out of range
    └── DataError (ValueError)       a file on disk is missing, truncated, foreign or mismatched
        ├── LogError                 a flight log
        └── CheckpointError          a model checkpoint

Each also derives from the built-in exception of its kind (ValueError, RuntimeError), so
`except ValueError` keeps catching the bad configurations and files.
"""

from __future__ import annotations

__all__ = ["TestbedError", "ConcurrentUseError", "ConfigError", "DataError", "LogError", "CheckpointError"]


class TestbedError(Exception):
    """Base of every error this project raises on purpose."""

    __test__ = False  # not a pytest test class, despite the name


class ConcurrentUseError(TestbedError, RuntimeError):
    """A second thread called into a simulator (or the env that holds it) while another thread
    was inside it: a simulator serves one thread at a time."""


class ConfigError(TestbedError, ValueError):
    """An argument, option or configuration is out of range; the message names it and what is allowed."""


class DataError(TestbedError, ValueError):
    """A file on disk is missing, truncated, foreign, or does not match what was asked for."""


class LogError(DataError):
    """A flight log is missing, truncated, foreign or of another schema version."""


class CheckpointError(DataError):
    """A checkpoint is missing, unreadable, unsafe, or does not match what was expected."""
