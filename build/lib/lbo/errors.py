"""The one exception type that entry points turn into a one-line message."""


class LboError(ValueError):
    """Bad input (config, data file, checkpoint); the message names the field and its form."""
