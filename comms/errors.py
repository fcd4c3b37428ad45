"""The one exception class of the ``comms`` package."""

from __future__ import annotations


class CommsError(ValueError):
    """A network that cannot be built or used as asked: unknown node or key, bad
    payload, a configuration that needs a callback nobody supplied. The message names
    what was wrong and what is allowed. A ``ValueError`` so that pydantic validators of
    the scenario schema can raise it and report it as a validation error."""
