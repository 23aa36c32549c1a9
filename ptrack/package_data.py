"""The files shipped in `ptrack/data` (the CMU joint limits, pose prior and smoothing tables, the bundled clip),
found beside this module rather than by the package's name.

`importlib.resources.files("ptrack")` looks the package up by its name, and that name can mean another folder:
run from the parent folder of a clone (whose root is a folder named `ptrack` without `__init__.py`) with ptrack
installed through an import hook (an editable install), `import ptrack` finds the clone's root as a namespace
package, the submodules still load from the install, and the data is looked for in the clone's root
(`FileNotFoundError: joint limits file not found: <cwd>/ptrack/data/cmu_limits.json`). This module's own file
is always the code that runs, so its folder holds the right data from any working directory.
"""

from __future__ import annotations

from pathlib import Path

DATA_DIR = Path(__file__).resolve().parent / "data"


def data_file(name: str) -> Path:
    """The path of the shipped file `name` (e.g. "cmu_limits.json") in ptrack/data."""
    return DATA_DIR / name
