"""The command line's contract for user errors, shared by the test modules that check it."""

from __future__ import annotations

from pathlib import Path

from ptrack.cli import main


def fail(capsys, out: Path, argv: list[str], *fragments: str) -> str:
    """Run argv; assert exit 2, one `ptrack: error:` line naming every fragment, no traceback, nothing on
    stdout, nothing written at `out` and no half-written folder beside it. -> the error line."""
    capsys.readouterr()  # what earlier calls in the test printed is not this call's
    rc = main(argv)
    captured = capsys.readouterr()
    err = captured.err
    assert rc == 2, f"exit {rc}, stderr: {err}"
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("ptrack: error: "), err
    assert "Traceback" not in err
    for f in fragments:
        assert f in lines[0], f"{f!r} not in {lines[0]!r}"
    assert captured.out == ""
    assert not out.exists(), f"{out} was written"
    if out.parent.exists():
        assert not any(".partial" in p.name for p in out.parent.iterdir())
    return lines[0]
