"""User-facing errors.

`InputError` marks a problem with what the user gave ptrack (a file, a config key, an array shape,
NaNs, a camera that sees nothing). The CLI prints its message and exits non-zero without a
traceback; any other exception is a bug and keeps its traceback. `log_to_stderr` sets the form of
its other messages.
"""

import logging


class InputError(ValueError):
    """Bad user input: the message names the offending file, key, line or shape."""


class EstimationError(RuntimeError):
    """An estimator produced an unusable result (e.g. non-finite poses). The CLI prints its message
    and exits 1; `ptrack evaluate` records the clip as failed and goes on."""


def log_to_stderr() -> None:
    """Log records of level WARNING and above to stderr as `ptrack: WARNING: message`, the command line's
    form: in the CLI's process, and in the worker processes of `ptrack evaluate --jobs`."""
    logging.basicConfig(level=logging.WARNING, format="ptrack: %(levelname)s: %(message)s")
