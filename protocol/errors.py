"""The one exception type every decoder and validator in `protocol` raises."""


class ProtocolError(ValueError):
    """A message, spec or log record is malformed.

    The message names the problem (which field, what was expected, what was found).
    Subclasses `ValueError`, so callers that already catch `ValueError` keep working.
    """


class SpecError(ProtocolError):
    """An oracle spec is invalid; the message starts with the path of the bad field."""
