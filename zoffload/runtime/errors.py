"""Named exit codes and the errors that map to them."""

from __future__ import annotations

from enum import IntEnum


class ExitCode(IntEnum):
    OK = 0
    FAILURE = 1  # an unexpected error (a bug): the traceback is logged
    CONFIG = 2  # bad command line, config file, config key or value
    DATA = 3  # a scan source or data file that cannot be read
    ZENOH = 4  # the Zenoh session could not be opened (bad endpoint, port in use)
    INTERRUPTED = 130  # a second SIGINT/SIGTERM forced the exit


class ConfigError(Exception):
    """Bad configuration; the message says which key and why."""


class ZenohSessionError(Exception):
    """The Zenoh session could not be opened with this configuration."""
