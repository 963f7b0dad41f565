"""Errors a user can cause (bad input, bad options): the CLI prints them as one line, exit 1."""


class UserError(Exception):
    """A problem with the user's input that deserves one clear line, not a traceback."""


class ContractError(UserError, ValueError):
    """A recording breaks the recording contract; the message names bag, topic, key or field."""
