"""The error every command reports as one line and exit status 2: input the user can fix.

Readers (:class:`~h3edge.io.sequence.DatasetError`), profiles (``ProfileError``) and checkpoints
(``CheckpointError``) subclass :class:`InputError`, so the command line catches them all without
importing the modules that raise them (a query client never loads torch). :class:`QueryError` is a
query the service refuses: the zenoh server replies with its message.
"""


class InputError(ValueError):
    """Bad input the user can fix (a file, a profile, a checkpoint): the message says what and where."""


class QueryError(InputError):
    """A query the service refuses or cannot answer; the message goes back to the client."""
