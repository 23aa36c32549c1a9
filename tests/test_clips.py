"""`ptrack.clips`: one parser of file lists (comma list, list file, glob) for every caller, whose errors name the
flag or config key the user typed: `--clips` (ptrack evaluate), `config key 'motion.clips'` (the motion model),
`--inputs` (ptrack batch)."""

from __future__ import annotations

from pathlib import Path

import pytest

from ptrack.clips import list_paths, parse_clips
from ptrack.errors import InputError
from ptrack.motion.motion_model import clip_paths
from ptrack.pipeline.batch_run import parse_inputs
from ptrack.pipeline.evaluate import evaluate

REPO = Path(__file__).resolve().parents[1]


def _files(folder: Path, *names: str) -> list[Path]:
    folder.mkdir(parents=True, exist_ok=True)
    out = []
    for n in names:
        (folder / n).write_text("x\n")
        out.append((folder / n).resolve())
    return out


def test_list_paths_comma_list_file_and_glob(tmp_path):
    a, b = _files(tmp_path / "d", "a.npz", "b.npz")
    assert list_paths("d/a.npz, d/b.npz", "--x", "item", tmp_path) == [a, b]
    (tmp_path / "d" / "list.txt").write_text("b.npz\n# a.npz\n\na.npz  # a comment\n")
    assert list_paths("d/list.txt", "--x", "item", tmp_path) == [b, a]  # relative to the list, in its order
    assert list_paths("d/*.npz", "--x", "item", tmp_path) == [a, b]  # sorted
    assert list_paths(str(tmp_path / "**" / "b.npz"), "--x", "item") == [b]
    # not a list where the caller says so: the file itself
    assert list_paths("d/list.txt", "--x", "item", tmp_path, is_list=lambda p: False) == [
        (tmp_path / "d" / "list.txt").resolve()
    ]


@pytest.mark.parametrize(
    ("spec", "error", "message"),
    [
        ("d/empty.txt", InputError, "--x 'd/empty.txt': the list names no item"),
        (" , ", InputError, "--x ' , ' names no item"),
        ("d/*.mp4", InputError, "--x 'd/*.mp4' matches no file or folder"),
        ("d/gone.npz", FileNotFoundError, "item not found: "),
    ],
)
def test_list_paths_errors_name_the_flag_and_the_noun(tmp_path, spec, error, message):
    _files(tmp_path / "d", "a.npz")
    (tmp_path / "d" / "empty.txt").write_text("# nothing here\n")
    with pytest.raises(error) as e:
        list_paths(spec, "--x", "item", tmp_path)
    assert str(e.value).startswith(message)


def test_parse_clips_names_its_caller(tmp_path):
    (tmp_path / "empty.txt").write_text("\n")
    with pytest.raises(InputError, match=r"^--clips 'empty.txt': the list names no clip$"):
        parse_clips("empty.txt", tmp_path)
    with pytest.raises(InputError, match=r"^config key 'motion.clips' 'empty.txt': the list names no clip$"):
        parse_clips("empty.txt", tmp_path, what="config key 'motion.clips'")
    _files(tmp_path, "10.asf")
    with pytest.raises(InputError, match=r"^--clips: clip .*10\.asf is not an \.amc file$"):
        parse_clips("10.asf", tmp_path)


def test_motion_clips_empty_list_names_the_config_key(tmp_path):
    """The motion model's clip list (`motion.clips`): an empty file says so, not a `--clips` flag."""
    empty = tmp_path / "golf.txt"
    empty.write_text("# no swing\n")
    with pytest.raises(InputError) as e:
        clip_paths((str(empty),))
    assert "config key 'motion.clips'" in str(e.value) and "names no clip" in str(e.value)
    assert "--clips" not in str(e.value)


def test_evaluate_clips_errors_name_the_flag(tmp_path):
    empty = tmp_path / "none.txt"
    empty.write_text("")
    with pytest.raises(InputError, match=r"^--clips '.*none.txt': the list names no clip$"):
        evaluate(REPO / "configs" / "eval_frame.yaml", str(empty), out=tmp_path / "out")
    with pytest.raises(InputError, match=r"^--clips '.*\*_99.amc' matches no file or folder$"):
        evaluate(REPO / "configs" / "eval_frame.yaml", str(tmp_path / "*_99.amc"), out=tmp_path / "out")
    assert not (tmp_path / "out").exists()


def test_batch_inputs_errors_name_the_flag(tmp_path):
    empty = tmp_path / "inputs.txt"
    empty.write_text("# later\n")
    with pytest.raises(InputError, match=r"^--inputs 'inputs.txt': the list names no input$"):
        parse_inputs("inputs.txt", tmp_path)
    with pytest.raises(InputError, match=r"^--inputs 'v/\*.mp4' matches no file or folder$"):
        parse_inputs("v/*.mp4", tmp_path)
    with pytest.raises(FileNotFoundError, match=r"^input not found: "):
        parse_inputs("gone.mp4", tmp_path)
    a, b = _files(tmp_path / "v", "a.mp4", "b.mp4")
    assert [i.path for i in parse_inputs("v/*.mp4", tmp_path)] == [a, b]
    notes = _files(tmp_path, "notes.md")[0]  # only .txt and .list files are lists of inputs
    assert [i.path for i in parse_inputs("notes.md", tmp_path)] == [notes]
