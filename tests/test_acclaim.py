"""Tests for ptrack.body.acclaim: ASF/AMC text parsing on the real CMU files and on malformed input."""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import pytest

from ptrack.body.acclaim import INCH_M, AmcFile, AsfFile, parse_amc, parse_asf
from ptrack.errors import InputError

# Every file of ../shared/data/cmu, with the frame counts its README lists.
CMU_SUBJECTS = ("01", "02", "05", "07", "09", "10", "16", "35", "49", "64", "118", "124", "131", "135")
CMU_FRAMES = {
    "01_01": 2751,
    "02_01": 343,
    "02_03": 173,
    "02_04": 483,
    "02_05": 1854,
    "02_07": 2251,
    "05_02": 1123,
    "05_04": 1199,
    "05_07": 1191,
    "07_05": 517,
    "09_06": 141,
    "10_01": 801,
    "10_02": 590,
    "10_03": 362,
    "16_01": 322,
    "16_03": 410,
    "16_05": 295,
    "35_01": 358,
    "49_18": 1102,
    "49_19": 957,
    "64_01": 448,
    "64_02": 493,
    "64_04": 412,
    "64_05": 387,
    "64_06": 529,
    "64_08": 364,
    "64_09": 452,
    "118_01": 714,
    "118_02": 685,
    "118_03": 497,
    "124_01": 643,
    "131_03": 1102,
    "131_07": 691,
    "131_09": 2293,
    "135_04": 1316,
    "135_07": 1472,
}
LF_SUBJECTS = {"05", "07", "09", "131", "135"}  # the README's LF-ending skeletons; the rest are CRLF


def dof_counts(asf: AsfFile) -> dict[str, int]:
    """The `parse_amc` argument for an ASF: root value count, then every bone with dofs."""
    return {"root": len(asf.root_order), **{b.name: len(b.dof) for b in asf.bones if b.dof}}


# A minimal valid ASF; malformed variants below edit single lines of it.
MINI_ASF = """\
# a tiny two-bone leg
:version 1.10
:name mini
:units
  mass 1.0
  length 0.45
  angle deg
:documentation
   free text that is ignored
:root
   order TX TY TZ RX RY RZ
   axis XYZ
   position 0 0 0
   orientation 0 0 0
:bonedata
  begin
     id 1
     name hip
     direction 0 -2 0   # not unit: the parser normalises it
     length 2.0
     axis 0 0 20 XYZ
    dof rx ry rz
    limits (-160.0 20.0)
           (-70.0 70.0)
           (-60.0 70.0)
  end
  begin
     id 2
     name knee
     direction 0 -1 0
     length 3.0
     axis 0 0 0 XYZ
    dof rx
    limits (0.0 170.0)
  end
:hierarchy
  begin
    root hip
    hip knee
  end
""".split("\n")  # noqa: SIM905 (the file as text reads better than a list of its lines)


def _line_of(lines: list[str], text: str) -> int:
    """1-based number of the first line containing `text`."""
    return next(i for i, line in enumerate(lines, start=1) if text in line)


def _write(tmp_path: Path, lines: list[str], name: str = "bad.asf", eol: str = "\n") -> Path:
    p = tmp_path / name
    p.write_bytes(eol.join(lines).encode())
    return p


# -- the minimal ASF ---------------------------------------------------------------------------


@pytest.mark.parametrize("eol", ["\n", "\r\n"])
def test_mini_asf_parses_fields(tmp_path, eol):
    asf = parse_asf(_write(tmp_path, MINI_ASF, "mini.asf", eol))
    assert asf.name == "mini"
    assert asf.length_unit == 0.45 and asf.angle_unit == "deg"
    assert asf.root_order == ("TX", "TY", "TZ", "RX", "RY", "RZ")
    assert asf.root_axis == "XYZ"
    assert [b.name for b in asf.bones] == ["hip", "knee"]
    hip, knee = asf.bones
    assert hip.direction == pytest.approx((0.0, -1.0, 0.0))  # normalised from (0, -2, 0)
    assert hip.length == 2.0 and hip.axis == (0.0, 0.0, 20.0) and hip.axis_order == "XYZ"
    assert hip.dof == ("rx", "ry", "rz")
    assert hip.limits == ((-160.0, 20.0), (-70.0, 70.0), (-60.0, 70.0))
    assert knee.dof == ("rx",) and knee.limits == ((0.0, 170.0),)
    assert asf.hierarchy == (("root", "hip"), ("hip", "knee"))


def test_mini_asf_without_limits_and_units_defaults(tmp_path):
    lines = [ln for ln in MINI_ASF if "limits" not in ln and not ln.strip().startswith("(")]
    lines = [ln for ln in lines if ln.strip() not in (":units", "mass 1.0", "length 0.45", "angle deg")]
    asf = parse_asf(_write(tmp_path, lines))
    assert asf.bones[0].limits == ((-math.inf, math.inf),) * 3
    assert asf.length_unit == 1.0 and asf.metres_per_unit == pytest.approx(INCH_M)


def test_mini_asf_infinite_limits_and_radians(tmp_path):
    lines = [ln.replace("(0.0 170.0)", "(-inf inf)").replace("angle deg", "angle rad") for ln in MINI_ASF]
    asf = parse_asf(_write(tmp_path, lines))
    assert asf.bones[1].limits == ((-math.inf, math.inf),)
    assert asf.angle_unit == "rad"


# -- malformed ASF: InputError naming the file and the line --------------------------------------


def _replace(lines: list[str], old: str, new: str) -> list[str]:
    i = _line_of(lines, old) - 1
    return lines[:i] + [lines[i].replace(old, new)] + lines[i + 1 :]


def _at(text: str, delta: int = 0):
    """Expected line: `delta` lines after the first line containing `text` (in the edited file)."""
    return lambda lines: _line_of(lines, text) + delta


MALFORMED_ASF = {
    # name: (edit of MINI_ASF, the line the message must name, words the message must contain)
    "bad number in direction": (
        lambda L: _replace(L, "direction 0 -1 0", "direction 0 -1.0.0 0"),
        _at("-1.0.0"),
        "numbers",
    ),
    "too few numbers in direction": (
        lambda L: _replace(L, "direction 0 -1 0", "direction 0 -1"),
        _at("direction 0 -1"),
        "expected 3",
    ),
    "nan length": (lambda L: _replace(L, "length 3.0", "length nan"), _at("length nan"), "non-finite"),
    "limits count mismatch": (  # named at the bone's `begin` line
        lambda L: [ln for ln in L if "(-60.0 70.0)" not in ln],
        _at("id 1", -1),
        "3 dofs but 2 limits",
    ),
    "too many limits": (
        lambda L: _replace(L, "limits (0.0 170.0)", "limits (0.0 170.0)\n    (1 2)"),
        _at("(1 2)"),
        "(1",
    ),
    "limits reversed": (lambda L: _replace(L, "(0.0 170.0)", "(170.0 0.0)"), _at("(170.0 0.0)"), "above"),
    "limits not a pair": (lambda L: _replace(L, "(0.0 170.0)", "(0.0 170.0 3)"), _at("(0.0 170.0 3)"), "(lo hi)"),
    "unknown dof": (lambda L: _replace(L, "dof rx ry rz", "dof rx ry rq"), _at("dof rx ry rq"), "rq"),
    "unknown bone field": (lambda L: _replace(L, "id 2", "colour 2"), _at("colour 2"), "colour"),
    "unknown bone in hierarchy": (lambda L: _replace(L, "hip knee", "hip kneee"), _at("hip kneee"), "kneee"),
    "unknown parent in hierarchy": (lambda L: _replace(L, "hip knee", "hipp knee"), _at("hipp knee"), "hipp"),
    "unclosed begin block": (  # hip's `end` removed: knee's `begin` comes inside hip's block
        lambda L: L[: _line_of(L, "id 2") - 3] + L[_line_of(L, "id 2") - 2 :],
        _at("id 2", -1),
        "'begin' inside",
    ),
    "unclosed last block": (  # knee's `end` removed: named at knee's `begin`
        lambda L: L[: _line_of(L, ":hierarchy") - 2] + L[_line_of(L, ":hierarchy") - 1 :],
        _at("id 2", -1),
        "never closed",
    ),
    "content before first keyword": (lambda L: ["hello"] + L, _at("hello"), "before the first"),
    "bad units length": (lambda L: _replace(L, "length 0.45", "length -0.45"), _at("length -0.45"), "positive"),
    "bad units angle": (lambda L: _replace(L, "angle deg", "angle grad"), _at("angle grad"), "deg or rad"),
    "bad axis order": (lambda L: _replace(L, "axis 0 0 20 XYZ", "axis 0 0 20 XYY"), _at("axis 0 0 20 XYY"), "XYY"),
    "bad root order": (lambda L: _replace(L, "order TX TY", "order TX QY"), _at("order TX QY"), "root order"),
    "data outside a block": (
        lambda L: _replace(L, ":bonedata", ":bonedata\n  name stray"),
        _at("name stray"),
        "outside",
    ),
}


@pytest.mark.parametrize("case", sorted(MALFORMED_ASF))
def test_malformed_asf_names_file_and_line(tmp_path, case):
    edit, expected_line, words = MALFORMED_ASF[case]
    lines = "\n".join(edit(list(MINI_ASF))).split("\n")
    assert lines != MINI_ASF
    p = _write(tmp_path, lines)
    with pytest.raises(InputError) as exc:
        parse_asf(p)
    msg = str(exc.value)
    assert f"{p}:{expected_line(lines)}:" in msg, msg
    assert words in msg, msg


def test_missing_bonedata_names_file_and_section(tmp_path):
    start, stop = _line_of(MINI_ASF, ":bonedata") - 1, _line_of(MINI_ASF, ":hierarchy") - 1
    lines = MINI_ASF[:start] + MINI_ASF[stop:]
    p = _write(tmp_path, lines)
    with pytest.raises(InputError, match=re.escape(str(p))) as exc:
        parse_asf(p)
    assert ":bonedata" in str(exc.value)


@pytest.mark.parametrize("section", [":hierarchy", ":root"])
def test_missing_required_section(tmp_path, section):
    lines = [ln.replace(section, ":renamed") for ln in MINI_ASF]
    with pytest.raises(InputError, match=section):
        parse_asf(_write(tmp_path, lines))


def test_bone_missing_from_hierarchy(tmp_path):
    lines = [ln for ln in MINI_ASF if ln.strip() != "hip knee"]
    with pytest.raises(InputError, match="knee"):
        parse_asf(_write(tmp_path, lines))


def test_bone_with_two_parents(tmp_path):
    lines = _replace(MINI_ASF, "hip knee", "hip knee\n    root knee")
    with pytest.raises(InputError, match="more than one parent"):
        parse_asf(_write(tmp_path, "\n".join(lines).split("\n")))


def test_binary_garbage_asf(tmp_path):
    p = tmp_path / "garbage.asf"
    p.write_bytes(b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR\xff\xfe\xfd" + bytes(range(256)))
    with pytest.raises(InputError, match=re.escape(str(p))) as exc:
        parse_asf(p)
    assert "not a text file" in str(exc.value)


def test_ascii_garbage_asf_names_line(tmp_path):
    p = tmp_path / "garbage.asf"
    p.write_bytes(b"\x00\x01\x02 junk\n\x03\x04\n")
    with pytest.raises(InputError, match=re.escape(f"{p}:1")):
        parse_asf(p)


def test_empty_asf(tmp_path):
    p = tmp_path / "empty.asf"
    p.write_text("")
    with pytest.raises(InputError, match="not an ASF"):
        parse_asf(p)


def test_missing_asf_file(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"nope\.asf"):
        parse_asf(tmp_path / "nope.asf")


def test_asf_path_is_a_directory(tmp_path):
    with pytest.raises(InputError, match="not a file"):
        parse_asf(tmp_path)


# -- the real CMU skeletons --------------------------------------------------------------------


def test_cmu_folder_has_the_listed_files(cmu_dir):
    asfs = {p.stem for p in (cmu_dir / "subjects").glob("*/*.asf")}
    amcs = {p.stem for p in (cmu_dir / "subjects").glob("*/*.amc")}
    assert asfs == set(CMU_SUBJECTS)
    assert amcs == set(CMU_FRAMES)


@pytest.mark.parametrize("subject", CMU_SUBJECTS)
def test_every_cmu_asf_parses(cmu_file, subject):
    p = cmu_file(f"{subject}.asf")
    raw = p.read_bytes()
    assert (b"\r\n" in raw) == (subject not in LF_SUBJECTS)  # both line-ending styles are exercised
    asf = parse_asf(p)
    assert len(asf.bones) == 30
    assert sum(len(b.dof) for b in asf.bones) == 56
    assert len(asf.root_order) == 6 and asf.root_axis == "XYZ"
    assert asf.length_unit == 0.45 and asf.angle_unit == "deg"
    assert abs(asf.metres_per_unit - 0.056444) < 1e-6
    assert len(asf.hierarchy) == 30
    assert {c for _, c in asf.hierarchy} == {b.name for b in asf.bones}
    for b in asf.bones:
        assert len(b.limits) == len(b.dof)
        assert np.linalg.norm(b.direction) == pytest.approx(1.0, abs=1e-9)
        assert b.length > 0
    assert [b.name for b in asf.bones if not b.dof] == ["lhipjoint", "rhipjoint"]


def test_cmu_64_lfemur_values(asf_64):
    asf = parse_asf(asf_64)
    assert asf.name == "VICON"
    b = {b.name: b for b in asf.bones}["lfemur"]
    assert b.direction == pytest.approx((0.34202, -0.939693, 0.0), abs=1e-5)
    assert b.length == pytest.approx(7.40817)
    assert b.axis == (0.0, 0.0, 20.0) and b.axis_order == "XYZ"
    assert b.dof == ("rx", "ry", "rz")
    assert b.limits == ((-160.0, 20.0), (-70.0, 70.0), (-60.0, 70.0))
    assert ("root", "lhipjoint") in asf.hierarchy and ("lhipjoint", "lfemur") in asf.hierarchy


def test_crlf_and_lf_copies_parse_identically(tmp_path, asf_64):
    raw = asf_64.read_bytes()
    lf = tmp_path / "64_lf.asf"
    lf.write_bytes(raw.replace(b"\r\n", b"\n"))
    a, b = parse_asf(asf_64), parse_asf(lf)
    assert a.bones == b.bones and a.hierarchy == b.hierarchy and a.length_unit == b.length_unit


def test_namespace_keyword_is_skipped(cmu_file):
    p = cmu_file("05.asf")
    assert b":namespace MODERNDANCE" in p.read_bytes()
    asf = parse_asf(p)
    assert asf.name == "Modern Dance"
    assert len(asf.bones) == 30 and asf.length_unit == 0.45


# -- AMC ---------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def counts_64(asf_64) -> dict[str, int]:
    return dof_counts(parse_asf(asf_64))


@pytest.mark.parametrize("clip", sorted(CMU_FRAMES))
def test_every_cmu_amc_parses_with_readme_frame_count(cmu_file, clip):
    asf = parse_asf(cmu_file(f"{clip.split('_')[0]}.asf"))
    counts = dof_counts(asf)
    amc = parse_amc(cmu_file(f"{clip}.amc"), counts)
    t = CMU_FRAMES[clip]
    assert isinstance(amc, AmcFile)
    np.testing.assert_array_equal(amc.frame_numbers, np.arange(1, t + 1))
    assert set(amc.values) == set(counts)
    for bone, n in counts.items():
        assert amc.values[bone].shape == (t, n) and amc.values[bone].dtype == np.float64
    assert np.isfinite(amc.values["root"]).all()


def test_amc_64_01_first_frame_values(amc_64_01, counts_64):
    amc = parse_amc(amc_64_01, counts_64)
    assert amc.frame_numbers.shape == (448,)
    np.testing.assert_array_equal(amc.values["root"][0], [-5.82914, 17.8741, 1.78981, -78.4182, 86.296, -96.1138])
    np.testing.assert_array_equal(amc.values["lfemur"][0], [-31.3742, 5.01646, -9.07132])
    np.testing.assert_array_equal(amc.values["rfingers"][0], [7.12502])
    assert amc.values["root"][1, 0] == -5.82902


def test_amc_02_01_frame_count(cmu_file):
    amc = parse_amc(cmu_file("02_01.amc"), dof_counts(parse_asf(cmu_file("02.asf"))))
    assert len(amc.frame_numbers) == 343


def _amc_head(amc_path: Path, n_lines: int) -> list[str]:
    with open(amc_path, encoding="utf-8") as f:
        return [next(f).rstrip("\r\n") for _ in range(n_lines)]


# 64_01 layout: 3 header lines, then per frame 1 number line + 29 bone lines.
FRAME_LINES = 30


def test_amc_against_wrong_dof_counts(amc_64_01, counts_64):
    wrong = dict(counts_64, rfemur=2)
    with pytest.raises(InputError, match="belong to this ASF") as exc:
        parse_amc(amc_64_01, wrong)
    msg = str(exc.value)
    assert "rfemur" in msg and "3 values" in msg and f"{amc_64_01}:" in msg


def test_amc_against_asf_with_extra_bone(amc_64_01, counts_64):
    with pytest.raises(InputError, match=r"missing bones.*tail.*belong to this ASF"):
        parse_amc(amc_64_01, dict(counts_64, tail=1))


def test_amc_against_asf_lacking_a_bone(amc_64_01, counts_64):
    fewer = {k: v for k, v in counts_64.items() if k != "ltoes"}
    with pytest.raises(InputError, match=r"'ltoes'.*belong to this ASF"):
        parse_amc(amc_64_01, fewer)


def test_amc_against_modified_real_asf(tmp_path, asf_64, amc_64_01):
    """An ASF whose rtoes has two dofs: the real AMC gives one value, which must not match."""
    text = asf_64.read_text()
    i = text.index("name rtoes")
    j = text.index("end", i)
    block = text[i:j].replace("dof rx", "dof rx rz").replace("limits (-90.0 20.0)", "limits (-90.0 20.0)\n (-5 5)")
    p = tmp_path / "64_mod.asf"
    p.write_text(text[:i] + block + text[j:])
    asf = parse_asf(p)
    assert {b.name: b.dof for b in asf.bones}["rtoes"] == ("rx", "rz")
    with pytest.raises(InputError, match=r"'rtoes' has 1 values, the ASF skeleton says 2"):
        parse_amc(amc_64_01, dof_counts(asf))


def test_amc_truncated_frame(tmp_path, amc_64_01, counts_64):
    lines = _amc_head(amc_64_01, 3 + FRAME_LINES + 10)  # frame 2 stops after 9 bones
    p = _write(tmp_path, lines, "trunc.amc", "\r\n")
    with pytest.raises(InputError) as exc:
        parse_amc(p, counts_64)
    msg = str(exc.value)
    assert f"{p}:{3 + FRAME_LINES + 1}" in msg  # the line of frame number 2
    assert "frame 2 is missing bones" in msg


def test_amc_truncated_line(tmp_path, amc_64_01, counts_64):
    """The file ends inside a bone line: lfemur of frame 1 has only two of its three values."""
    lines = _amc_head(amc_64_01, 3 + FRAME_LINES - 4) + ["lfemur -31.3742 5.01646"]
    p = _write(tmp_path, lines, "cut.amc")
    with pytest.raises(InputError, match=re.escape(f"{p}:{len(lines)}") + ".*'lfemur' has 2 values"):
        parse_amc(p, counts_64)


def test_amc_complete_prefix_parses(tmp_path, amc_64_01, counts_64):
    lines = _amc_head(amc_64_01, 3 + 2 * FRAME_LINES)
    amc = parse_amc(_write(tmp_path, lines, "two.amc"), counts_64)
    np.testing.assert_array_equal(amc.frame_numbers, [1, 2])


@pytest.mark.parametrize("bad", ["-5.8x914", "nan", "1e999"])
def test_amc_bad_number_names_line(tmp_path, amc_64_01, counts_64, bad):
    lines = _amc_head(amc_64_01, 3 + 2 * FRAME_LINES)
    lines[4] = lines[4].replace("-5.82914", bad)
    p = _write(tmp_path, lines, "badnum.amc")
    with pytest.raises(InputError, match=re.escape(f"{p}:5")):
        parse_amc(p, counts_64)


def test_amc_bone_given_twice(tmp_path, amc_64_01, counts_64):
    lines = _amc_head(amc_64_01, 3 + FRAME_LINES)
    lines.insert(6, lines[5])
    p = _write(tmp_path, lines, "twice.amc")
    with pytest.raises(InputError, match=re.escape(f"{p}:7") + ".*given twice"):
        parse_amc(p, counts_64)


def test_amc_data_before_first_frame(tmp_path, amc_64_01, counts_64):
    lines = _amc_head(amc_64_01, 3 + FRAME_LINES)
    del lines[3]  # the frame number "1"
    p = _write(tmp_path, lines, "noframe.amc")
    with pytest.raises(InputError, match=re.escape(f"{p}:4") + ".*before the first frame"):
        parse_amc(p, counts_64)


def test_amc_with_no_frames(tmp_path, counts_64):
    p = _write(tmp_path, [":FULLY-SPECIFIED", ":DEGREES", ""], "empty.amc")
    with pytest.raises(InputError, match="no frames"):
        parse_amc(p, counts_64)


def test_amc_binary_garbage(tmp_path, counts_64):
    p = tmp_path / "garbage.amc"
    p.write_bytes(b"\xff\xfe\x00\x81" * 100)
    with pytest.raises(InputError, match=re.escape(str(p))):
        parse_amc(p, counts_64)


def test_missing_amc_file(tmp_path, counts_64):
    with pytest.raises(FileNotFoundError, match=r"nope\.amc"):
        parse_amc(tmp_path / "nope.amc", counts_64)
