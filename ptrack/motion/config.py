"""The config section of the motion model (`motion:`, `ptrack fit-motion` and `method: pca`) and its checks.
Composed into the run's config by `ptrack.pipeline.config`."""

from __future__ import annotations

from dataclasses import dataclass, field

from ptrack.errors import InputError
from ptrack.settings import setting

#: the golf swing's key postures (Urtasun, Fleet & Fua 2004, fig. 2), rules of `ptrack.motion.key_postures`
GOLF_KEY_POSTURES = {
    "start": "rest before top",  # start of upswing: the hands still, before the upswing's fastest motion
    "top": "first max height",  # top of upswing: the hands' first high point
    "hit": "first min height after top",  # ball hit: the hands' low point of the downswing
    "end": "min speed after hit within 0.8 s",  # end of downswing: the hands' slowest, at the finish
}


@dataclass(frozen=True)
class MotionConfig:
    """`ptrack fit-motion`: a time-warped PCA motion model of one motion type (`ptrack.motion.motion_model`)."""

    clips: tuple[str, ...] = setting((), "training clips: AMC files, or one text file listing them; .asf beside each")
    joints: tuple[str, ...] = setting(("lradius", "rradius"), "tracked point of the key postures: their mean (wrists)")
    exclude: tuple[str, ...] = setting(
        ("*fingers", "*thumb", "*hand", "*toes"), "dofs left out of the model besides the root's (as model.freeze)"
    )
    key_postures: dict[str, str] = field(
        default_factory=lambda: dict(GOLF_KEY_POSTURES),
        metadata={
            "help": "name -> rule, in temporal order (ptrack/motion/key_postures.py); an override replaces them all"
        },
    )
    smooth_s: float = setting(0.05, "Gaussian smoothing (std, seconds) of the tracked point before the rules")
    prominence: float = setting(0.02, "first/last extrema: least prominence, as a fraction of the signal's range")
    rest_fraction: float = setting(0.05, "rest: slower than this fraction of the clip's top speed")
    samples: int = setting(200, "N: normalised times per swing")
    components: int = setting(4, "m: eigen-motions kept (at most the number of clips - 1)")
    model_file: str | None = setting(
        None, "where fit-motion writes the model and pca reads it; null = ~/.cache/ptrack/motion/<name>.npz"
    )


def validate_motion(m: MotionConfig) -> None:
    """Value checks of the `motion:` section (the clip count is checked when fitting)."""
    from ptrack.motion.key_postures import parse_rules

    if m.samples < 2:
        raise InputError(f"config key 'motion.samples' must be >= 2, got {m.samples}")
    if m.components < 1:
        raise InputError(f"config key 'motion.components' must be >= 1, got {m.components}")
    if not m.joints:
        raise InputError("config key 'motion.joints' must name at least one joint")
    if m.smooth_s < 0:
        raise InputError(f"config key 'motion.smooth_s' must be >= 0, got {m.smooth_s}")
    if not 0 <= m.prominence < 1:
        raise InputError(f"config key 'motion.prominence' must be in [0, 1), got {m.prominence}")
    if not 0 < m.rest_fraction < 1:
        raise InputError(f"config key 'motion.rest_fraction' must be in (0, 1), got {m.rest_fraction}")
    parse_rules(m.key_postures)
