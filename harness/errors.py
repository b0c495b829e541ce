"""Errors the user sees as one line, with a non-zero exit, before any long work when possible."""


class RetainError(Exception):
    """A user-facing error: its message is one line naming the bad value and what is valid."""


class DemoFileError(RetainError):
    """A demo file that is corrupt, incomplete, or was made for other settings."""


class NonFiniteLoss(RetainError):
    """Training produced a NaN or infinite loss."""
