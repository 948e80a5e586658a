"""The one error a user sees for a scenario problem."""


class ConfigError(Exception):
    """A scenario problem a user can fix: the message names the file, key path and what is allowed."""
