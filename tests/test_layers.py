"""The package's layers (docs/architecture.md): imports run one way, down the data flow.

Every module of ptrack/ is read with `ast` (every import: module level, inside functions, under
`if TYPE_CHECKING:`) and fails the test when it
- imports a module of a higher layer (no import "back up"),
- is part of one estimator and imports another estimator (`ptrack.estimators.<name>`; the registry
  `ptrack/estimators/__init__.py`, which puts them together, may import them all),
- imports a `_private` name from another module (`from x import _name`; a module's own helpers stay
  inside it, helpers shared inside a subpackage are public names).
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PKG = Path(__file__).resolve().parents[1] / "ptrack"

#: lowest first; a module belongs to the layer of the longest prefix naming it (a module or a package)
LAYERS: list[tuple[str, tuple[str, ...]]] = [
    (
        "utilities",
        ("ptrack.errors", "ptrack.checks", "ptrack.package_data", "ptrack.threads", "ptrack.settings", "ptrack.clips"),
    ),
    ("body", ("ptrack.body",)),
    ("observe", ("ptrack.observe",)),
    ("costs", ("ptrack.costs",)),
    ("optim", ("ptrack.optim",)),
    ("hypotheses", ("ptrack.hypotheses",)),
    ("motion", ("ptrack.motion",)),
    ("problem", ("ptrack.problem",)),
    ("estimators", ("ptrack.estimators",)),
    ("io", ("ptrack.io",)),
    ("pipeline", ("ptrack.pipeline",)),
    ("entry points", ("ptrack", "ptrack.cli")),  # `ptrack/__init__.py` (the public API) and the command line
]


def module_names(root: Path) -> dict[str, Path]:
    """Dotted module name -> file, for every .py under the package folder `root`."""
    out = {}
    for path in sorted(root.rglob("*.py")):
        parts = (root.name, *path.relative_to(root).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = path
    return out


def layer_of(module: str) -> int | None:
    """Index into LAYERS of `module` (its longest matching prefix; the package itself names only its
    `__init__.py`), None when no layer names it."""
    best, length = None, -1
    for i, (_, prefixes) in enumerate(LAYERS):
        for p in prefixes:
            if (module == p or ("." in p and module.startswith(p + "."))) and len(p) > length:
                best, length = i, len(p)
    return best


def imports(module: str, path: Path, modules: dict[str, Path]) -> list[tuple[int, str, list[str]]]:
    """(line, imported module, names imported from it) of every import of a package module in `path`.
    `from pkg import sub` counts as importing the module `pkg.sub` when it is one."""
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    root = next(iter(modules)).split(".")[0]
    found = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
        if isinstance(node, ast.Import):
            found += [(node.lineno, a.name, []) for a in node.names if a.name.split(".")[0] == root]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            if target.split(".")[0] != root:
                continue
            plain = []
            for a in node.names:
                sub = f"{target}.{a.name}"
                if sub in modules:
                    found.append((node.lineno, sub, []))
                else:
                    plain.append(a.name)
            if plain:
                found.append((node.lineno, target, plain))
    return found


def estimator_of(module: str) -> str | None:
    """`ptrack.estimators.<name>...` -> name; None for the registry and for modules outside estimators."""
    parts = module.split(".")
    return parts[2] if len(parts) > 2 and parts[1] == "estimators" else None


def violations(root: Path) -> list[str]:
    """Every broken rule in the package folder `root`, one line each."""
    modules = module_names(root)
    out = []
    for module, path in modules.items():
        mine = layer_of(module)
        if mine is None:
            out.append(f"{module}: in no layer (add it to LAYERS in tests/test_layers.py)")
            continue
        for line, target, names in imports(module, path, modules):
            where = f"{path.relative_to(root.parent)}:{line}"
            theirs = layer_of(target)
            if theirs is not None and theirs > mine:
                up = f"{module} ({LAYERS[mine][0]}) imports {target} ({LAYERS[theirs][0]})"
                out.append(f"{where}: {up}, a higher layer")
            a, b = estimator_of(module), estimator_of(target)
            if a is not None and target.startswith(f"{root.name}.estimators") and b != a:
                out.append(f"{where}: estimator {a} imports {target}: no estimator imports another")
            private = [n for n in names if n.startswith("_") and not (n.startswith("__") and n.endswith("__"))]
            if private and target != module:
                out.append(f"{where}: {module} imports private {', '.join(private)} from {target}")
    return out


def test_imports_flow_one_way():
    found = violations(PKG)
    assert not found, "layer rules broken (docs/architecture.md):\n" + "\n".join(found)


def test_every_layer_is_a_folder_or_module_of_the_package():
    modules = module_names(PKG)
    for name, prefixes in LAYERS:
        for p in prefixes:
            assert p in modules, f"layer {name}: {p} is no module of ptrack"


@pytest.mark.parametrize(
    ("files", "expected"),
    [
        ({"body/a.py": "from ptrack.pipeline import b\n", "pipeline/b.py": ""}, "a higher layer"),
        ({"body/a.py": "def f():\n    import ptrack.pipeline.b\n", "pipeline/b.py": ""}, "a higher layer"),
        (
            {"body/a.py": "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from ptrack.io.b import X\n"},
            "a higher layer",
        ),
        ({"estimators/kjs/a.py": "from ptrack.estimators.frame import f\n", "estimators/frame.py": ""}, "another"),
        ({"estimators/batch.py": "from ptrack.estimators import frame\n", "estimators/frame.py": ""}, "another"),
        ({"body/a.py": "from ptrack.body.b import _helper\n", "body/b.py": ""}, "private _helper"),
        ({"costs/a.py": "from .b import _helper\n", "costs/b.py": ""}, "private _helper"),
        ({"loose.py": ""}, "in no layer"),
    ],
)
def test_each_rule_is_caught(tmp_path, files, expected):
    root = tmp_path / "ptrack"
    for sub in ("", "body", "observe", "costs", "optim", "hypotheses", "motion", "estimators", "io", "pipeline"):
        (root / sub).mkdir(parents=True, exist_ok=True)
        (root / sub / "__init__.py").touch()
    for name in ("errors", "checks", "package_data", "problem", "cli"):
        (root / f"{name}.py").touch()
    for name, text in files.items():
        (root / name).parent.mkdir(parents=True, exist_ok=True)
        (root / name).write_text(text)
    found = violations(root)
    assert len(found) == 1 and expected in found[0], found


def test_allowed_imports_pass(tmp_path):
    root = tmp_path / "ptrack"
    for sub in ("", "body", "estimators", "estimators/kjs", "pipeline"):
        (root / sub).mkdir(parents=True, exist_ok=True)
        (root / sub / "__init__.py").touch()
    (root / "estimators" / "__init__.py").write_text("from ptrack.estimators import frame, kjs\n")  # the registry
    (root / "estimators" / "frame.py").write_text("from ptrack.body import a\n")
    (root / "estimators" / "kjs" / "model.py").write_text("from ptrack.estimators.kjs.step import merge\n")
    (root / "estimators" / "kjs" / "step.py").write_text("def _own():\n    pass\n")
    (root / "body" / "a.py").write_text("from ptrack.body.b import __all__\n")  # a dunder, not a private name
    (root / "body" / "b.py").write_text("__all__ = []\n")
    (root / "cli.py").write_text("from ptrack import __version__\nfrom ptrack.pipeline import run\n")
    (root / "pipeline" / "run.py").write_text("from ptrack.estimators import frame\n")
    assert violations(root) == []


def test_public_api_table_matches_its_type_checking_imports():
    """`ptrack/__init__.py`: every lazily exported name resolves to the object its table names, and the
    `if TYPE_CHECKING:` block imports exactly the table's names from the same modules (what type checkers see)."""
    import ptrack

    tree = ast.parse((PKG / "__init__.py").read_text())
    block = next(n for n in tree.body if isinstance(n, ast.If) and ast.unparse(n.test) == "TYPE_CHECKING")
    typed = {a.name: n.module for n in block.body if isinstance(n, ast.ImportFrom) for a in n.names}
    assert typed == ptrack._EXPORTS
    for name, module in ptrack._EXPORTS.items():
        assert getattr(ptrack, name) is getattr(__import__(module, fromlist=[name]), name), name
    assert {"read_keypoints", "select_person", "read_camera", "detect"} <= set(ptrack.__all__)
