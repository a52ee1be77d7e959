"""Errors that reach the user as one clear line."""


class SkyviewError(Exception):
    """Base class: the message is shown to the user as is."""


class BadInput(SkyviewError):
    """The user's input cannot be used (missing or corrupt file, impossible parameter, ...).

    The CLI turns it into a one-line message and exit code 2.
    """
