"""`setting`, the field of every config key: its default and one line of help. The config's sections are frozen
dataclasses beside what they configure (a method's in its estimator, the motion model's in `motion/`, the shared
cost terms' in `costs/`); `ptrack.pipeline.config` composes them into `RunConfig`."""

from __future__ import annotations

import typing
from dataclasses import field

_T = typing.TypeVar("_T")


def setting(default: _T, help: str) -> _T:
    """A config key's field: its default and one line of help, which `config_reference` (`ptrack config --list`,
    docs/config.md) reads from the field's metadata. The measurements behind the defaults are in
    docs/notes/config-history.md."""
    return field(default=default, metadata={"help": help})
