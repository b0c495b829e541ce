"""Errors the user sees as one line, with a non-zero exit, before any long work when possible."""

from suites.base import SuiteError


class RetainError(Exception):
    """A user-facing error: its message is one line naming the bad value and what is valid."""


class DemoFileError(RetainError):
    """A demo file that is corrupt, incomplete, or was made for other settings."""


class NonFiniteLoss(RetainError):
    """Training produced a NaN or infinite loss."""


USER_ERRORS = (RetainError, SuiteError)
"""Printed as one line without a traceback: the harness's own errors and the suites' (raised
upstream, where the harness cannot be imported)."""
