"""Property-based tests (hypothesis) of the input readers: any bytes or any YAML either load or raise
`InputError`, never another exception. Bounded examples to stay fast in the suite; for a longer local
run: `HYPOTHESIS_PROFILE=long python -m pytest tests/test_fuzz.py`."""

from __future__ import annotations

import contextlib
import os
from pathlib import Path

import pytest
import yaml

hypothesis = pytest.importorskip("hypothesis")
from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

from ptrack.body.acclaim import parse_amc, parse_asf  # noqa: E402
from ptrack.errors import InputError  # noqa: E402
from ptrack.observe.observations import Observations  # noqa: E402
from ptrack.pipeline.config import load_config  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
ASF = (REPO / "ptrack" / "data" / "10.asf").read_bytes()
AMC = (REPO / "ptrack" / "data" / "10_02.amc").read_bytes()[:4000]

settings.register_profile(
    "suite",
    max_examples=60,
    deadline=None,
    derandomize=True,
    database=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
settings.register_profile(
    "long",
    max_examples=5000,
    deadline=None,
    database=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "suite"))


def _mutations(base: bytes):
    """Random bytes, and the real file with a slice replaced by random bytes or cut short."""
    return st.one_of(
        st.binary(max_size=400),
        st.tuples(st.integers(0, len(base)), st.integers(0, 40), st.binary(max_size=40)).map(
            lambda t: base[: t[0]] + t[2] + base[t[0] + t[1] :]
        ),
        st.integers(0, len(base)).map(lambda n: base[:n]),
    )


def _loads_or_input_error(fn, *args) -> None:
    with contextlib.suppress(InputError):
        fn(*args)


@given(_mutations(ASF))
def test_asf_parser(tmp_path_factory, data):
    p = tmp_path_factory.mktemp("asf") / "x.asf"
    p.write_bytes(data)
    _loads_or_input_error(parse_asf, p)


@given(_mutations(AMC))
def test_amc_parser(tmp_path_factory, data):
    p = tmp_path_factory.mktemp("amc") / "x.amc"
    p.write_bytes(data)
    _loads_or_input_error(parse_amc, p, {"root": 6, "lfemur": 3, "ltibia": 1, "head": 3})


@given(st.binary(max_size=600))
def test_observations_npz_reader(tmp_path_factory, data):
    p = tmp_path_factory.mktemp("obs") / "x.npz"
    p.write_bytes(data)
    _loads_or_input_error(Observations.load_npz, p)


_yaml_values = st.recursive(
    st.one_of(st.none(), st.booleans(), st.integers(-(10**30), 10**30), st.floats(), st.text(max_size=8)),
    lambda inner: st.one_of(st.lists(inner, max_size=3), st.dictionaries(st.text(max_size=8), inner, max_size=3)),
    max_leaves=8,
)
_keys = st.sampled_from(
    [
        "method",
        "seed",
        "out_dir",
        "name",
        "data",
        "data.stride",
        "data.stop",
        "camera.focal_px",
        "observations.missing",
        "model.freeze",
        "model.keypoints",
        "kjs.modes",
        "batch.tol",
        "x.y",
    ]
)


def _nested(flat: dict) -> dict:
    out: dict = {}
    for key, value in flat.items():
        *sections, last = key.split(".")
        node = out
        for s in sections:
            node = node.setdefault(s, {}) if isinstance(node.get(s, {}), dict) else {}
        node[last] = value
    return out


@given(
    st.one_of(
        st.text(max_size=200),
        st.dictionaries(_keys, _yaml_values, max_size=4).map(lambda d: yaml.safe_dump(_nested(d))),
    )
)
def test_config_loader(tmp_path_factory, text):
    p = tmp_path_factory.mktemp("cfg") / "c.yaml"
    p.write_bytes(text.encode("utf-8", errors="replace"))
    _loads_or_input_error(load_config, p)


@given(_keys, st.text(max_size=30))
def test_config_overrides(key, value):
    _loads_or_input_error(load_config, REPO / "configs" / "demo.yaml", [f"{key}={value}"])
