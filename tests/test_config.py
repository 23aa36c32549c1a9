"""Tests for ptrack.pipeline.config: defaults, YAML + dotted overrides, typed errors naming the dotted key,
path resolution, value checks, and the dump/load round trip."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest
import yaml

from ptrack.errors import InputError
from ptrack.pipeline.config import (
    CameraConfig,
    DataConfig,
    ObservationsConfig,
    RunConfig,
    dump_yaml,
    load_config,
    parse_override,
    to_dict,
)

REPO = Path(__file__).resolve().parents[1]
DEMO = REPO / "configs" / "demo.yaml"
EVAL = REPO / "configs" / "eval_frame.yaml"
ASF = REPO / "ptrack" / "data" / "10.asf"
AMC = REPO / "ptrack" / "data" / "10_02.amc"
DATA = [f"data.asf={ASF}", f"data.amc={AMC}"]


def _write(path: Path, text: str) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text, encoding="utf-8")
    return path


def _raises_naming(key: str, *args, **kwargs) -> InputError:
    with pytest.raises(InputError) as info:
        load_config(*args, **kwargs)
    assert key in str(info.value), f"{key!r} not named in: {info.value}"
    return info.value


# ---------------------------------------------------------------- defaults and keys


def test_defaults_load():
    cfg = load_config(None, DATA)
    expected = RunConfig(data=DataConfig(asf=str(ASF), amc=str(AMC)))
    assert cfg == expected
    assert cfg.method == "frame" and cfg.seed == 0 and cfg.out_dir is None
    assert cfg.name == "run"  # no YAML file: the default config name
    assert cfg.data.stride == 4 and cfg.data.start == 0 and cfg.data.stop is None
    assert isinstance(cfg.camera.focal_px, float)
    assert cfg.camera.width is None and cfg.camera.height is None  # 640 x 480 when simulating, else the file's


def test_defaults_without_data_paths_name_the_missing_key():
    _raises_naming("data.asf")
    _raises_naming("data.amc", None, [f"data.asf={ASF}"])


def test_observation_file_makes_amc_optional(tmp_path):
    cfg = load_config(None, [f"data.asf={ASF}", "observations.file=obs.npz"], cwd=tmp_path)
    assert cfg.data.amc == "" and cfg.observations.file == str(tmp_path / "obs.npz")


REQUIRED_KEYS = (
    "method",
    "seed",
    "out_dir",
    "data.asf",
    "data.amc",
    "data.start",
    "data.stop",
    "data.stride",
    "camera.distance_m",
    "camera.azimuth_deg",
    "camera.elevation_deg",
    "camera.focal_px",
    "camera.width",
    "camera.height",
    "observations.noise_px",
    "observations.missing",
    "observations.outliers",
)


@pytest.mark.parametrize("key", REQUIRED_KEYS)
def test_required_keys_exist(key):
    node = to_dict(RunConfig())
    for part in key.split("."):
        assert isinstance(node, dict) and part in node, f"config has no key {key!r}"
        node = node[part]


def test_shipped_configs_load():
    for path in (DEMO, EVAL):
        cfg = load_config(path)
        assert cfg.name == path.stem
        assert Path(cfg.data.asf) == ASF and Path(cfg.data.amc) == AMC
    demo = load_config(DEMO)
    assert demo.camera.distance_m == 6.0 and demo.observations.missing == 0.05 and demo.frame.iterations == 30
    assert load_config(EVAL).data.stop == 360


# ---------------------------------------------------------------- YAML + overrides


def test_yaml_and_dotted_overrides(tmp_path):
    path = _write(
        tmp_path / "mine.yaml",
        f"""
seed: 3
data:
  asf: {ASF}
  amc: {AMC}
  stride: 2
camera:
  focal_px: 800
observations:
  noise_px: 1.5
""",
    )
    cfg = load_config(
        path,
        [
            "seed=7",
            "data.stop=100",
            "camera.azimuth_deg=-45",
            "observations.outliers=0.1",
            "model.freeze=[ '*toes' ]",
            "model.keypoints={head: head, pelvis: root}",
        ],
    )
    assert cfg.name == "mine"
    assert cfg.seed == 7  # the override wins over the file
    assert cfg.data.stride == 2 and cfg.data.stop == 100 and cfg.data.start == 0
    assert cfg.camera.focal_px == 800.0 and isinstance(cfg.camera.focal_px, float)  # int -> float
    assert cfg.camera.azimuth_deg == -45.0
    assert cfg.camera.distance_m == CameraConfig().distance_m  # untouched default
    assert cfg.observations == dataclasses.replace(ObservationsConfig(), noise_px=1.5, outliers=0.1)
    assert cfg.model.freeze == ("*toes",)
    assert cfg.model.keypoints == {"head": "head", "pelvis": "root"}


def test_override_single_string_becomes_tuple():
    assert load_config(None, [*DATA, "model.freeze=lfingers"]).model.freeze == ("lfingers",)
    assert load_config(None, [*DATA, "model.freeze='*toes'"]).model.freeze == ("*toes",)  # quoted: not an alias


def test_later_override_wins_and_null_override():
    cfg = load_config(DEMO, ["data.stride=2", "data.stride=3", "data.stop=50", "data.stop=null"])
    assert cfg.data.stride == 3 and cfg.data.stop is None


def test_empty_sections_and_empty_file_use_defaults(tmp_path):
    path = _write(tmp_path / "e.yaml", f"data:\n  asf: {ASF}\n  amc: {AMC}\ncamera:\nobservations: null\n")
    cfg = load_config(path)
    assert cfg.camera == CameraConfig() and cfg.observations == ObservationsConfig()
    _raises_naming("data.asf", _write(tmp_path / "empty.yaml", ""))


def test_parse_override():
    assert parse_override("a.b=3") == ("a.b", 3)
    assert parse_override("a= x ") == ("a", "x")
    assert parse_override("a=") == ("a", None)
    assert parse_override("a=[1, 2]") == ("a", [1, 2])
    for bad in ("seed", "=3", "a..b=1", ".a=1"):
        with pytest.raises(InputError, match="override"):
            parse_override(bad)
    with pytest.raises(InputError, match="not valid YAML"):
        parse_override("a=[1, 2")


# ---------------------------------------------------------------- unknown keys and wrong types


def test_unknown_top_level_key(tmp_path):
    _raises_naming("'colour'", DEMO, ["colour=red"])
    path = _write(tmp_path / "u.yaml", f"data:\n  asf: {ASF}\n  amc: {AMC}\nspeed: 3\n")
    _raises_naming("'speed'", path)


def test_unknown_nested_key(tmp_path):
    _raises_naming("'camera.fov'", DEMO, ["camera.fov=60"])
    _raises_naming("'frame.iters'", DEMO, ["frame.iters=3"])
    path = _write(tmp_path / "u.yaml", f"data:\n  asf: {ASF}\n  amc: {AMC}\n  fps: 30\n")
    _raises_naming("'data.fps'", path)


def test_section_given_a_scalar():
    _raises_naming("camera", DEMO, ["camera=5"])
    _raises_naming("seed", DEMO, ["seed.x=1"])


@pytest.mark.parametrize(
    "override, key",
    [
        ("camera.focal_px=abc", "camera.focal_px"),  # string for a float
        ("observations.noise_px=[1, 2]", "observations.noise_px"),
        ("data.stride=1.5", "data.stride"),  # float for an int
        ("seed=2.0", "seed"),
        ("data.stride=true", "data.stride"),  # bool for an int
        ("camera.width=false", "camera.width"),
        ("camera.focal_px=true", "camera.focal_px"),  # bool for a float
        ("progress=1", "progress"),  # int for a bool
        ("method=3", "method"),  # int for a string
        ("camera.focal_px=null", "camera.focal_px"),  # null where not allowed
        ("data.stride=null", "data.stride"),
        ("method=null", "method"),
        ("model.freeze=5", "model.freeze"),
    ],
)
def test_wrong_type_names_the_key(override, key):
    _raises_naming(key, DEMO, [override])


@pytest.mark.parametrize(
    "override, key",
    [
        ("data.stop=abc", "data.stop"),  # string for an int-or-null
        ("data.stop=1.5", "data.stop"),
        ("out_dir=5", "out_dir"),  # int for a string-or-null
        ("observations.file=[a, b]", "observations.file"),
        ("model.keypoints=[head]", "model.keypoints"),  # list for a dict-or-null
        ("model.keypoints={head: 3}", "model.keypoints"),  # dict-or-null with a wrong value type
    ],
)
def test_wrong_type_for_nullable_key_names_the_key(override, key):
    # Optional (`X | None`) keys go through the union branch of _check_type; a wrong type there must
    # still be an InputError naming the key, not a crash.
    _raises_naming(key, DEMO, [override])


def test_wrong_type_in_yaml_file(tmp_path):
    path = _write(tmp_path / "t.yaml", f"data:\n  asf: {ASF}\n  amc: {AMC}\n  start: first\n")
    _raises_naming("data.start", path)


# ---------------------------------------------------------------- paths


def test_yaml_paths_relative_to_yaml_folder(tmp_path, monkeypatch):
    monkeypatch.chdir(REPO)  # a cwd different from the YAML's folder
    path = _write(
        tmp_path / "cfgs" / "p.yaml",
        "data:\n  asf: ../mocap/10.asf\n  amc: clips/10_02.amc\nobservations:\n  file: obs.npz\nout_dir: ../runs/one\n",
    )
    cfg = load_config(path)
    assert cfg.data.asf == str(tmp_path / "mocap" / "10.asf")
    assert cfg.data.amc == str(tmp_path / "cfgs" / "clips" / "10_02.amc")
    assert cfg.observations.file == str(tmp_path / "cfgs" / "obs.npz")
    assert cfg.out_dir == str(tmp_path / "runs" / "one")


def test_override_paths_relative_to_cwd(tmp_path, monkeypatch):
    cfg = load_config(DEMO, ["data.asf=a/10.asf", "out_dir=runs/x"], cwd=tmp_path)
    assert cfg.data.asf == str(tmp_path / "a" / "10.asf")
    assert cfg.out_dir == str(tmp_path / "runs" / "x")
    assert cfg.data.amc == str(AMC)  # still the YAML's, resolved against configs/
    monkeypatch.chdir(tmp_path)
    cfg = load_config(DEMO, ["data.amc=b/10_02.amc", "observations.file=o.npz"])
    assert cfg.data.amc == str(tmp_path / "b" / "10_02.amc")
    assert cfg.observations.file == str(tmp_path / "o.npz")


def test_absolute_paths_kept(tmp_path):
    asf = tmp_path / "x" / "10.asf"
    path = _write(tmp_path / "cfgs" / "a.yaml", f"data:\n  asf: {asf}\n  amc: {AMC}\n")
    assert load_config(path).data.asf == str(asf)
    assert load_config(path, [f"data.asf={asf}"], cwd=REPO).data.asf == str(asf)


# ---------------------------------------------------------------- value checks


@pytest.mark.parametrize(
    "override, key",
    [
        ("data.stride=0", "data.stride"),
        ("data.stride=-2", "data.stride"),
        ("data.stop=0", "data.stop"),  # stop <= start
        ("data.start=-1", "data.start"),
        ("observations.noise_px=-0.5", "observations.noise_px"),
        ("observations.missing=1.5", "observations.missing"),
        ("observations.outliers=-0.1", "observations.outliers"),
        ("method=kjs_magic", "method"),
        ("camera.focal_px=0", "camera.focal_px"),
        ("camera.distance_m=-1", "camera.distance_m"),
        ("camera.width=0", "camera.width"),
        ("dtype=float16", "dtype"),
        ("frame.init=zero", "frame.init"),
        ("frame.iterations=0", "frame.iterations"),
        ("costs.sigma_px=0", "costs.sigma_px"),
        ("costs.loss=tukey", "costs.loss"),
        ("costs.swap_cost=-1", "costs.swap_cost"),
        ("costs.swap_cost=nan", "costs.swap_cost"),
        ("batch.smooth_loss=tukey", "batch.smooth_loss"),
        ("kjs.prior_tail=l2", "kjs.prior_tail"),
    ],
)
def test_value_checks_name_the_key(override, key):
    _raises_naming(key, DEMO, [override])


def test_stop_equal_to_start_is_refused():
    _raises_naming("data.stop", DEMO, ["data.start=10", "data.stop=10"])
    assert load_config(DEMO, ["data.start=10", "data.stop=11", "data.stride=1"]).data.stop == 11


# ---------------------------------------------------------------- bad files


def test_missing_file(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"nothere\.yaml"):
        load_config(tmp_path / "nothere.yaml")


def test_invalid_yaml_names_the_file(tmp_path):
    path = _write(tmp_path / "broken.yaml", "data: {asf: [1, 2\n  amc: x\n")
    with pytest.raises(InputError, match=r"broken\.yaml"):
        load_config(path)


def test_yaml_list_is_refused(tmp_path):
    path = _write(tmp_path / "list.yaml", "- seed: 1\n- method: frame\n")
    with pytest.raises(InputError, match=r"list\.yaml.*mapping"):
        load_config(path)


def test_non_utf8_yaml_is_refused(tmp_path):
    path = tmp_path / "bin.yaml"
    path.write_bytes(b"seed: \xff\xfe\x00\x01\n")
    with pytest.raises(InputError, match=r"bin\.yaml"):
        load_config(path)


# ---------------------------------------------------------------- dump / round trip


def test_dump_yaml_round_trips(tmp_path):
    cfg = load_config(
        DEMO,
        [
            "seed=5",
            "data.stop=48",
            f"out_dir={tmp_path / 'out'}",
            "observations.outliers=0.2",
            "model.keypoints={head: head, l_knee: lfemur, r_knee: rfemur}",
            "costs.loss=huber",
            "frame.init=rest",
        ],
    )
    text = dump_yaml(cfg)
    assert isinstance(yaml.safe_load(text), dict)
    path = _write(tmp_path / "elsewhere" / "config.yaml", text)
    again = load_config(path)
    assert to_dict(again) == to_dict(cfg)
    assert again == cfg
    assert again.name == "demo"  # the original config's name, not the dumped file's stem


def test_dump_yaml_round_trips_defaults(tmp_path):
    cfg = load_config(None, DATA)
    again = load_config(_write(tmp_path / "d.yaml", dump_yaml(cfg)))
    assert to_dict(again) == to_dict(cfg)


def test_to_dict_is_plain():
    d = to_dict(load_config(DEMO))
    assert isinstance(d["model"]["freeze"], list)
    assert set(d) == {f.name for f in dataclasses.fields(RunConfig)}
    # plain data only: YAML safe_dump accepts it
    assert yaml.safe_load(yaml.safe_dump(d)) == d


def test_configs_are_frozen():
    cfg = load_config(DEMO)
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.seed = 3  # type: ignore[misc]
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.data.stride = 1  # type: ignore[misc]


def test_amc_override_takes_the_skeleton_beside_it(tmp_path, caplog):
    sub = tmp_path / "subjects" / "10"
    sub.mkdir(parents=True)
    for f in ("10.asf", "10_02.amc"):
        (sub / f).write_bytes((REPO / "ptrack" / "data" / f).read_bytes())
    cfg = load_config(REPO / "configs" / "demo.yaml", [f"data.amc={sub / '10_02.amc'}"])
    assert cfg.data.asf == str(sub / "10.asf") and cfg.data.amc == str(sub / "10_02.amc")
    assert [r.getMessage() for r in caplog.records] == [
        f"data.amc is {sub / '10_02.amc'}: using the skeleton beside it, {sub / '10.asf'} "
        "(set data.asf to choose another)"
    ]
    caplog.clear()  # both given: as given, silently
    cfg = load_config(REPO / "configs" / "demo.yaml", [f"data.amc={sub / '10_02.amc'}", f"data.asf={ASF}"])
    assert cfg.data.asf == str(ASF) and caplog.records == []
    cfg = load_config(REPO / "configs" / "demo.yaml", [f"data.amc={ASF.parent / '10_02.amc'}"])
    assert cfg.data.asf == str(ASF) and caplog.records == []  # the config's own skeleton is the one beside


def test_amc_override_without_a_skeleton_beside_it_keeps_the_config_one(tmp_path, caplog):
    (tmp_path / "10_02.amc").write_bytes((REPO / "ptrack" / "data" / "10_02.amc").read_bytes())
    cfg = load_config(REPO / "configs" / "demo.yaml", [f"data.amc={tmp_path / '10_02.amc'}"])
    assert cfg.data.asf == str(ASF)
    assert [r.getMessage() for r in caplog.records] == [
        f"data.amc is {tmp_path / '10_02.amc'} but no skeleton is beside it: keeping data.asf {ASF} "
        "(set data.asf to choose)"
    ]


def test_overrides_as_a_mapping_of_values(tmp_path, monkeypatch):
    """From Python: {dotted.key: value} as the values are (no YAML reading: "01" stays a string, a path with ": "
    stays a path), a Path for a path key, relative paths from the working directory; types still checked."""
    monkeypatch.chdir(tmp_path)
    cfg = load_config(
        DEMO,
        {
            "camera.name": "01",
            "observations.file": Path("a b: c.json"),
            "seed": 3,
            "model.freeze": ["*toes"],
            "keyframes.sigma_deg": 2,
        },
    )
    assert cfg.camera.name == "01" and cfg.seed == 3 and cfg.model.freeze == ("*toes",)
    assert cfg.observations.file == str(tmp_path / "a b: c.json")
    assert cfg.keyframes.sigma_deg == 2
    assert load_config(DEMO, {"seed": 3}) == load_config(DEMO, ["seed=3"])
    with pytest.raises(InputError, match=r"config key 'camera\.name' must be a string, got 1"):
        load_config(DEMO, {"camera.name": 1})
    with pytest.raises(InputError, match=r"unknown config key 'camera\.nam'"):
        load_config(DEMO, {"camera.nam": "x"})
