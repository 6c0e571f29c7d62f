"""Every settings file goes through one typed schema: wrong types, non-finite and out-of-range values of
every field of every schema are refused with one line naming the field; the CLIs exit 2 before motion."""

from __future__ import annotations

import dataclasses
import json
import math
import typing

import pytest
from conftest import one_line_message, refusal
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import dssp_data.observation  # noqa: F401
import dssp_data.pointcloud.extrinsics  # noqa: F401
import dssp_deploy.manifest  # noqa: F401  (defines the manifest's schema)
import dssp_train.config  # noqa: F401
import hardware.calibration.charuco  # noqa: F401  (the ChArUco board's schema)
import hardware.camera.profiles
import hardware.recorder  # noqa: F401
import hardware.safety  # noqa: F401
from dssp_core.errors import ConfigError
from dssp_core.schema import Settings, Spec, _union_args, all_schemas, setting

IDENTITY = [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]]
SAMPLES = {
    "CalibrationFile": {"camera_to_base": IDENTITY},
    "ColorProfile": {"width": 640, "height": 480, "fps": 30},
    "CameraProfile": hardware.camera.profiles.load_profile("d435").to_dict(),
}
"""A valid JSON object for each schema whose fields have no defaults."""

EXPECTED = {
    "SafetyConfig",
    "PointCloudConfig",
    "RecordThresholds",
    "CalibrationFile",
    "DiffusionConfig",
    "ModelConfig",
    "TrainConfig",
    "RunConfig",
    "CameraProfile",
}


def valid_sample(cls) -> dict:
    if cls.__name__ in SAMPLES:
        return json.loads(json.dumps(SAMPLES[cls.__name__]))
    try:
        return cls().to_dict()
    except TypeError:
        pytest.fail(f"{cls.__name__} has required fields: add a valid sample to SAMPLES")


def schema_fields():
    out = []
    for cls in all_schemas():
        hints = typing.get_type_hints(cls)
        for f in dataclasses.fields(cls):
            out.append(
                pytest.param(cls, f.name, hints[f.name], f.metadata.get("spec", Spec()), id=f"{cls.__name__}.{f.name}")
            )
    return out


def test_every_settings_file_kind_has_a_schema():
    names = {cls.__name__ for cls in all_schemas()}
    assert EXPECTED <= names, f"missing schemas: {EXPECTED - names}"


@pytest.mark.parametrize("cls", all_schemas(), ids=lambda c: c.__name__)
def test_valid_sample_round_trips(cls):
    values = valid_sample(cls)
    built = cls.from_dict(values)
    assert cls.from_dict(json.loads(json.dumps(built.to_dict()))) == built


# ------------------------------------------------------------------------------ wrong values
def _core(tp):
    args = _union_args(tp)
    if args is None:
        return tp, False
    rest = [a for a in args if a is not type(None)]
    return rest[0], type(None) in args


JSON_SCALARS = st.one_of(
    st.text(max_size=8),
    st.integers(-(10**6), 10**6),
    st.floats(allow_nan=True, allow_infinity=True),
    st.booleans(),
    st.none(),
)
JSON_VALUES = st.one_of(
    JSON_SCALARS, st.lists(JSON_SCALARS, max_size=3), st.dictionaries(st.text(max_size=4), JSON_SCALARS, max_size=2)
)


def wrong_type(tp):
    """Values that are not of the annotated type (never a valid value, whatever the range)."""
    core, optional = _core(tp)
    nothing = st.nothing() if optional else st.none()
    containers = st.one_of(
        st.lists(JSON_SCALARS, max_size=3), st.dictionaries(st.text(max_size=4), JSON_SCALARS, max_size=2)
    )
    if core is bool:
        return st.one_of(
            st.text(max_size=8),
            st.sampled_from(["false", "true", "0", "no"]),
            st.integers(),
            st.floats(),
            nothing,
            containers,
        )
    if core is int:
        return st.one_of(st.text(max_size=8), st.booleans(), st.floats(), nothing, containers)
    if core is float:
        return st.one_of(
            st.text(max_size=8),
            st.sampled_from(["0.1", "1"]),
            st.booleans(),
            nothing,
            containers,
            st.sampled_from([math.nan, math.inf, -math.inf]),
        )
    if core is str:
        return st.one_of(st.integers(), st.floats(), st.booleans(), nothing, containers)
    origin = typing.get_origin(core)
    if origin in (list, tuple):
        items = typing.get_args(core)
        item_wrong = wrong_type(items[0])
        fixed = origin is tuple and items and items[-1] is not Ellipsis
        n = len(items) if fixed else 2
        bad_items = st.lists(item_wrong, min_size=1, max_size=1).map(lambda bad: bad + [None] * 0)
        with_bad_item = st.tuples(bad_items, st.integers(0, n - 1)).map(lambda t: [t[0][0]] * n)
        strategies = [
            st.text(max_size=8),
            st.integers(),
            st.floats(),
            st.booleans(),
            nothing,
            with_bad_item,
            st.dictionaries(st.text(max_size=4), JSON_SCALARS, max_size=2),
        ]
        if fixed:
            strategies.append(st.lists(st.floats(-1, 1), min_size=0, max_size=len(items) - 1))
        return st.one_of(*strategies)
    if dataclasses.is_dataclass(core):
        return st.one_of(
            st.text(max_size=8), st.integers(), st.floats(), st.booleans(), nothing, st.lists(JSON_SCALARS, max_size=3)
        )
    if core is typing.Any or typing.get_origin(core) is dict:
        return st.nothing()
    raise AssertionError(f"no wrong-type strategy for {tp!r}")


def out_of_range(tp, spec: Spec):
    """Values of the right type outside the field's range or choices (st.nothing() if it has none)."""
    core, _ = _core(tp)
    origin = typing.get_origin(core)
    if origin in (list, tuple):
        items = typing.get_args(core)
        fixed = origin is tuple and items and items[-1] is not Ellipsis
        n = len(items) if fixed else max(spec.min_length or 1, 1)
        inner = out_of_range(items[0], dataclasses.replace(spec, min_length=None, max_length=None))
        wrong_len = st.nothing()
        if not fixed and spec.max_length is not None:
            wrong_len = st.just([_inside(items[0], spec)] * (spec.max_length + 1))
        elif not fixed and spec.min_length:
            wrong_len = st.just([_inside(items[0], spec)] * (spec.min_length - 1))
        return st.one_of(inner.map(lambda v: [v] * n), wrong_len)
    if core not in (int, float):
        if core is str and spec.choices:
            return st.text(max_size=8).filter(lambda s: s not in spec.choices)
        return st.nothing()
    options = []
    low = spec.ge if spec.ge is not None else spec.gt
    high = spec.le if spec.le is not None else spec.lt
    if core is int:
        if spec.choices:
            options.append(st.integers(-1000, 1000).filter(lambda v: v not in spec.choices))
        if low is not None:
            options.append(
                st.integers(max_value=math.ceil(low) - (0 if spec.gt is not None and low == int(low) else 1)).filter(
                    lambda v: not spec.in_range(v)
                )
            )
        if high is not None:
            options.append(st.integers(min_value=math.floor(high)).filter(lambda v: not spec.in_range(v)))
    else:
        if low is not None:
            options.append(
                st.floats(max_value=low, allow_nan=False, allow_infinity=False).filter(lambda v: not spec.in_range(v))
            )
        if high is not None:
            options.append(
                st.floats(min_value=high, allow_nan=False, allow_infinity=False).filter(lambda v: not spec.in_range(v))
            )
    return st.one_of(*options) if options else st.nothing()


def _inside(tp, spec: Spec):
    low = spec.ge if spec.ge is not None else (spec.gt if spec.gt is not None else 0)
    return tp(low + 1) if spec.in_range(tp(low + 1)) else tp(low)


def _assert_refused(cls, name: str, value) -> None:
    values = valid_sample(cls)
    values[name] = value
    with pytest.raises(ConfigError) as info:
        cls.from_dict(values)
    message = one_line_message(info)
    assert f"{cls.SECTION}.{name}" in message or name in message, message


@pytest.mark.parametrize("cls, name, tp, spec", schema_fields())
@settings(
    max_examples=25,
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.filter_too_much],
)
@given(data=st.data())
def test_wrong_type_is_refused_naming_the_field(cls, name, tp, spec, data):
    strategy = wrong_type(tp)
    if strategy.is_empty:
        pytest.fail(f"{cls.__name__}.{name}: the schema has no wrong values for {tp!r}")
    _assert_refused(cls, name, data.draw(strategy))


@pytest.mark.parametrize("cls, name, tp, spec", schema_fields())
@settings(
    max_examples=25,
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.filter_too_much],
)
@given(data=st.data())
def test_out_of_range_is_refused_naming_the_field(cls, name, tp, spec, data):
    strategy = out_of_range(tp, spec)
    core, _ = _core(tp)
    if strategy.is_empty:
        # Only booleans, free text, nested sections and objects have no range.
        assert core in (bool, str) or dataclasses.is_dataclass(core) or typing.get_origin(core) is dict, (
            f"{cls.__name__}.{name} ({tp!r}) declares no range: give it one with setting(ge=..., le=...)"
        )
        return
    _assert_refused(cls, name, data.draw(strategy))


def test_every_number_has_a_physical_range():
    """A number with no upper bound would let a unit mistake through (mm for m, deg for rad)."""
    for cls in all_schemas():
        hints = typing.get_type_hints(cls)
        for f in dataclasses.fields(cls):
            core, _ = _core(hints[f.name])
            if typing.get_origin(core) in (list, tuple):
                core = typing.get_args(core)[0]
                core, _ = _core(core)
                if typing.get_origin(core) is tuple:
                    core = typing.get_args(core)[0]
            spec = f.metadata.get("spec", Spec())
            if core in (int, float):
                assert spec.choices or (
                    (spec.ge is not None or spec.gt is not None) and (spec.le is not None or spec.lt is not None)
                ), f"{cls.__name__}.{f.name} has no range"


def test_unknown_and_missing_keys():
    from dssp_data.pointcloud.extrinsics import CalibrationFile
    from hardware.safety import SafetyConfig

    with pytest.raises(ConfigError, match="unknown safety setting.*max_joint_stp"):
        SafetyConfig.from_dict({"max_joint_stp": 0.1})
    with pytest.raises(ConfigError, match="lack camera_to_base"):
        CalibrationFile.from_dict({"frame": "base"})
    with pytest.raises(ConfigError, match="must be a JSON object"):
        SafetyConfig.from_dict([1, 2])


def test_messages_name_field_value_and_range():
    from hardware.safety import SafetyConfig

    with pytest.raises(ConfigError) as info:
        SafetyConfig.from_dict({"disable_on_exit": "false"})
    assert str(info.value) == "safety.disable_on_exit must be true or false (a JSON boolean), got 'false'"
    with pytest.raises(ConfigError) as info:
        SafetyConfig.from_dict({"limit_margin": "0.1"})
    assert str(info.value) == "safety.limit_margin must be a finite number in [0, 0.5) rad, got '0.1'"


def test_schema_refuses_an_annotation_it_cannot_check():
    @dataclasses.dataclass
    class Odd(Settings):
        value: set = setting(default_factory=set)

    with pytest.raises(TypeError, match="cannot check"):
        Odd()
    from dssp_core import schema

    schema._REGISTRY.remove(Odd)


# ------------------------------------------------------------------------------ the CLIs
@pytest.mark.parametrize(
    "content, field",
    [
        ({"disable_on_exit": "false"}, "safety.disable_on_exit"),
        ({"limit_margin": "0.1"}, "safety.limit_margin"),
        ({"max_joint_step": 2.0}, "safety.max_joint_step"),
        ({"camera_timeout": float("nan")}, "safety.camera_timeout"),
        ({"deadline_hold": 1}, "safety.deadline_hold"),
    ],
)
def test_dssp_run_refuses_a_bad_safety_file_before_anything_opens(tmp_path, capsys, monkeypatch, content, field):
    from hardware.cli import run

    opened = []
    monkeypatch.setattr("hardware.piper.piper_robot.PiperRobot.connect", lambda self: opened.append("robot"))
    path = tmp_path / "safety.json"
    path.write_text(json.dumps(content).replace("NaN", "NaN"))
    code = run.main(["--model", str(tmp_path / "no-model"), "--safety", str(path), "--quiet"])
    line = refusal((code, *capsys.readouterr()))
    assert field in line and str(path) in line
    assert opened == []


@pytest.mark.parametrize(
    "flag, content, field",
    [
        ("--pointcloud", {"n_points": "1024"}, "pointcloud.n_points"),
        ("--pointcloud", {"crop_min": [0, 0, -500]}, "pointcloud.crop_min[2]"),
        ("--pointcloud", {"use_color": "yes"}, "pointcloud.use_color"),
        ("--extrinsics", {"camera_to_base": IDENTITY, "frame": 3}, "calibration.frame"),
        ("--extrinsics", {"camera_to_base": [[1, 0, 0, 0]]}, "calibration.camera_to_base"),
    ],
)
def test_dssp_run_refuses_bad_settings_files(tmp_path, capsys, flag, content, field):
    from hardware.cli import run

    path = tmp_path / "settings.json"
    path.write_text(json.dumps(content))
    code = run.main(["--model", str(tmp_path / "no-model"), flag, str(path), "--quiet"])
    assert field in refusal((code, *capsys.readouterr()))


@pytest.mark.parametrize(
    "argv, words",
    [
        (["--camera", "foo"], "unknown camera 'foo'"),
        (["--control-rate", "0"], "--control-rate must be in [0.1, 1000] Hz"),
        (["--control-rate", "nan"], "--control-rate must be in [0.1, 1000] Hz"),
        (["--control-rate", "1e-300"], "--control-rate must be in [0.1, 1000] Hz"),
        (["--max-steps", "0"], "--max-steps must be at least 1"),
        (["--threads", "0"], "--threads must be in [1, "),
        (["--threads", "100000"], "--threads must be in [1, "),
    ],
)
def test_dssp_run_flags_are_checked_first(tmp_path, capsys, argv, words):
    from hardware.cli import run

    code = run.main(["--model", str(tmp_path / "no-model"), "--quiet", *argv])
    assert words in refusal((code, *capsys.readouterr()))


def test_dssp_run_refuses_a_step_faster_than_the_arm(tmp_path, capsys):
    from hardware.cli import run

    path = tmp_path / "safety.json"
    path.write_text(json.dumps({"max_joint_step": 0.4}))
    code = run.main(["--model", str(tmp_path / "no-model"), "--safety", str(path), "--control-rate", "20", "--quiet"])
    line = refusal((code, *capsys.readouterr()))
    assert "rad/s" in line and "max_joint_step" in line


@pytest.mark.parametrize(
    "flag, content, field",
    [
        ("--thresholds", {"camera_age": "0.2"}, "thresholds.camera_age"),
        ("--thresholds", {"late_tick": 5}, "thresholds.late_tick"),
        ("--pointcloud", {"voxel_size": 10}, "pointcloud.voxel_size"),
    ],
)
def test_dssp_record_refuses_bad_settings_files(tmp_path, capsys, flag, content, field):
    from dssp_sim.teleop import record_main

    path = tmp_path / "settings.json"
    path.write_text(json.dumps(content))
    out = tmp_path / "rec.zarr"
    code = record_main(["--out", str(out), flag, str(path), "--quiet", "--auto", "--episodes", "1"])
    assert field in refusal((code, *capsys.readouterr()))
    assert not out.exists()


@pytest.mark.parametrize(
    "argv, words",
    [
        (["--camera", "foo"], "unknown camera 'foo'"),
        (["--control-rate", "0"], "--control-rate must be in [0.1, 1000] Hz"),
    ],
)
def test_dssp_record_flags_are_checked_first(tmp_path, capsys, argv, words):
    from hardware.cli import record

    out = tmp_path / "rec.zarr"
    code = record.main(["--out", str(out), "--quiet", "--can", "can0", "--camera", "tabletop", *argv])
    assert words in refusal((code, *capsys.readouterr()))
    assert not out.exists()


@pytest.mark.parametrize(
    "override, field",
    [
        ("model.d_model=abc", "model.d_model"),
        ("model.d_model=64.5", "model.d_model"),
        ("model.d_model=true", "model.d_model"),
        ("train.lr=NaN", "train.lr"),
        ("model.n_action_steps=0", "model.n_action_steps"),
        ("model.diffusion.clip_sample=1", "model.diffusion.clip_sample"),
    ],
)
def test_dssp_train_set_is_type_checked(tmp_path, capsys, override, field):
    from conftest import write_arm_dataset

    from dssp_train.cli import train

    data = tmp_path / "d.zarr"
    write_arm_dataset(data, n_episodes=2, steps=10, n_points=16)
    code = train.main(["--data", str(data), "--preset", "tiny", "--out", str(tmp_path / "run"), "--set", override])
    line = refusal((code, *capsys.readouterr()))
    assert field in line and override in line
