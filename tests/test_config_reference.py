"""The config reference: every key has one line of help, `ptrack config --list` prints them, and docs/config.md
is what `python scripts/config_reference.py` makes from the dataclasses (it cannot drift from them)."""

from __future__ import annotations

import dataclasses
import importlib.util
from pathlib import Path

import pytest

from ptrack.cli import main
from ptrack.pipeline.config import KjsMethodConfig, RunConfig, config_reference, load_config, sections, to_dict

REPO = Path(__file__).resolve().parents[1]


def _generator():
    spec = importlib.util.spec_from_file_location("config_reference", REPO / "scripts" / "config_reference.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _leaves(cls, prefix: str = "") -> list[str]:
    out = []
    for f in dataclasses.fields(cls):
        default = f.default_factory() if f.default_factory is not dataclasses.MISSING else f.default
        out += _leaves(type(default), f"{prefix}{f.name}.") if dataclasses.is_dataclass(default) else [prefix + f.name]
    return out


def test_docs_config_md_is_generated_from_the_dataclasses():
    text = (REPO / "docs" / "config.md").read_text(encoding="utf-8")
    generator = _generator()
    assert generator.render(text) == text, "docs/config.md is out of date: run python scripts/config_reference.py"
    for key in _leaves(RunConfig):
        assert f"| `{key}` |" in text


def test_every_key_has_one_line_of_help():
    keys = config_reference()
    assert sorted(k.key for k in keys) == sorted(_leaves(RunConfig))
    for k in keys:
        assert k.help.strip() and "\n" not in k.help, k.key
        assert len(f"{k.key} = {k.default}  ({k.type})  {k.help}".split("\n")) == 1, k.key


def test_the_listed_defaults_read_back_as_overrides():
    """`key = default` as printed is a valid override that gives the default config: the list can be copied."""
    default = to_dict(RunConfig())
    for k in config_reference():
        cfg = load_config(None, [f"{k.key}={k.default}"], run=False)
        assert to_dict(cfg) == {**default, "name": "run"}, k.key


def test_config_list_kjs_lists_every_kjs_key(capsys):
    assert main(["config", "--list", "kjs"]) == 0
    out, err = capsys.readouterr()
    lines = out.splitlines()
    assert [line.split(" = ")[0] for line in lines] == [f"kjs.{f.name}" for f in dataclasses.fields(KjsMethodConfig)]
    assert "kjs.modes = 8  (int)  K: mixture modes kept per frame" in lines
    assert err == ""


def test_config_list_without_a_section_lists_every_key(capsys):
    assert main(["config", "--list"]) == 0
    listed = [line.split(" = ")[0] for line in capsys.readouterr().out.splitlines()]
    assert sorted(listed) == sorted(_leaves(RunConfig))


@pytest.mark.parametrize("section", ["kjz", "kjs.modes", "method"])
def test_config_list_unknown_section_is_one_error_line(capsys, section):
    assert main(["config", "--list", section]) == 2
    out, err = capsys.readouterr()
    assert out == ""
    assert err.splitlines() == [
        f"ptrack: error: unknown config section {section!r} (sections: {', '.join(sections())})"
    ]
