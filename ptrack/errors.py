"""User-facing errors.

`InputError` marks a problem with what the user gave ptrack (a file, a config key, an array shape,
NaNs, a camera that sees nothing). The CLI prints its message and exits non-zero without a
traceback; any other exception is a bug and keeps its traceback.
"""


class InputError(ValueError):
    """Bad user input: the message names the offending file, key, line or shape."""


class EstimationError(RuntimeError):
    """An estimator produced an unusable result (e.g. non-finite poses). The CLI prints its message
    and exits 1; `ptrack evaluate` records the clip as failed and goes on."""
