"""Values read back from licalib's files are checked against their types (``filetypes``)."""

from __future__ import annotations

import copy
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from licalib_cli.errors import ConfigError, LicalibError
from licalib_cli.filetypes import FileValueError, described, numbers, typed
from licalib_cli.results import CalibrationResult
from licalib_cli.sections import ExtraTerms, SensorCheck, SplitHalf
from licalib_cli.truth import Truth

GOLDEN = Path(__file__).parents[1] / "golden" / "result_v1.yaml"


@pytest.mark.parametrize(
    ("hint", "value", "expected"),
    [
        (float, 3, 3.0),
        (float, ".inf", None),
        (float, None, "nan"),
        (float, True, None),
        (int, 3, 3),
        (int, 3.0, None),
        (int, False, None),
        (str, "a", "a"),
        (str, 1, None),
        (bool, True, True),
        (bool, 1, None),
        (float | None, None, None),
        (float | None, "x", None),
        (tuple[float, ...], [1, 2.5], (1.0, 2.5)),
        (tuple[float, ...], 5, None),
        (tuple[float, float, float], [1, 2], None),
        (tuple[float, float, float], [1, 2, 3], (1.0, 2.0, 3.0)),
        (tuple[str, ...], ["a", 1], None),
        (dict[str, tuple[float | None, ...]], {"a": [1, None]}, {"a": (1.0, None)}),
        (dict[str, tuple[float | None, ...]], {"a": ["x"]}, None),
    ],
)
def test_typed_takes_what_the_annotation_allows(hint: Any, value: Any, expected: Any) -> None:
    if expected is None and value is not None:
        with pytest.raises(FileValueError) as info:
            typed(value, hint, "k")
        err = info.value
        assert err.key == "k" or err.key.startswith("k.")  # the key, or the element's
        assert err.key != "k" or err.problem.endswith(f", not {described(hint)}")
    elif expected == "nan":  # the JSON export's null for a non-finite number
        assert math.isnan(typed(value, hint, "k"))
    else:
        assert typed(value, hint, "k") == expected


def test_yaml_infinities_and_nans_are_numbers() -> None:
    data = yaml.safe_load("a: .inf\nb: .nan\n")
    assert typed(data["a"], float, "a") == math.inf
    assert math.isnan(typed(data["b"], float, "b"))
    with pytest.raises(FileValueError, match="all finite"):
        numbers([1.0, data["a"], 0.0], "t", 3, finite=True)


def test_the_key_of_a_nested_value_names_each_level() -> None:
    golden = yaml.safe_load(GOLDEN.read_text())
    sensor = golden["consistency"]["sensors"][0]
    bad = copy.deepcopy(sensor)
    bad["patterns"][0]["p_value"] = "small"
    with pytest.raises(FileValueError) as info:
        SensorCheck.from_dict(bad, "consistency.sensors.0")
    assert info.value.key == "consistency.sensors.0.patterns.0.p_value"
    assert info.value.problem == "is 'small', not a number"
    del bad["rms"]
    with pytest.raises(FileValueError, match=r"`consistency.sensors.0.rms` is missing"):
        SensorCheck.from_dict(bad, "consistency.sensors.0")


def test_a_section_written_by_licalib_reads_back_equal() -> None:
    split = SplitHalf("agree", "", 10.0, 0.4, 3.1, 7, 0.87, compared=("time_offset",))
    assert SplitHalf.from_dict(split.to_dict()) == split
    terms = ExtraTerms(reference_ns=1_700_000_004_000_000_123, clock_drift=2.8e-4)
    back = ExtraTerms.from_dict(terms.to_dict())
    assert back == terms and isinstance(back.reference_ns, int)


def _leaves(node: Any, path: tuple[Any, ...] = ()) -> list[tuple[Any, ...]]:
    out = [path] if path else []
    if isinstance(node, dict):
        for k, v in node.items():
            out += _leaves(v, (*path, k))
    elif isinstance(node, list):
        for i, v in enumerate(node):
            if isinstance(v, dict | list):
                out += _leaves(v, (*path, i))
    return out


def test_no_value_of_the_wrong_type_ends_in_anything_but_a_config_error() -> None:
    """Every key of the golden result, replaced by values of other types: either the file
    still reads (the value was of an allowed type) or one ConfigError says which key."""
    golden = yaml.safe_load(GOLDEN.read_text())
    refused = 0
    for path in _leaves(golden):
        for value in ("abc", 5, [1], None, {"a": 1}, True, [[1, 2]]):
            data = copy.deepcopy(golden)
            node = data
            for k in path[:-1]:
                node = node[k]
            node[path[-1]] = value
            try:
                CalibrationResult.from_dict(data)
            except LicalibError as err:
                assert isinstance(err, ConfigError), (path, value)
                refused += 1
    assert refused > 500  # most replacements are refused; the rest are of an allowed type


def test_the_truth_file_names_the_file_and_the_key(tmp_path: Path) -> None:
    truth = tmp_path / "truth.yaml"
    truth.write_text("schema_version: 1\nseed: 4.5\nextrinsic: {time_offset_s: .nan}\n")
    with pytest.raises(ConfigError) as info:
        Truth.load(truth)
    text = str(info.value)
    assert text.startswith(f"In the truth file {truth}, `extrinsic.time_offset_s` is nan")
    truth.write_text("schema_version: 1\nseed: 4.5\n")
    with pytest.raises(ConfigError, match=r"`seed` is 4\.5, not a whole number or null"):
        Truth.load(truth)
    truth.write_text("schema_version: true\n")
    with pytest.raises(ConfigError, match="schema_version True"):
        Truth.load(truth)


def test_a_quaternion_is_normalised_and_a_bad_one_refused() -> None:
    d = {"schema_version": 1, "extrinsic": {"rotation_quaternion": [0, 0, 0, 1.0000004]}}
    rot = CalibrationResult.from_dict(d).extrinsic.rotation
    assert np.allclose(rot, np.eye(3), atol=1e-12)
    d["extrinsic"]["rotation_quaternion"] = [0, 0, 0, 2]
    with pytest.raises(FileValueError, match="not a unit quaternion"):
        CalibrationResult.from_dict(d)


def test_lidar_intrinsics_of_one_length_each_and_none_missing() -> None:
    beams = {
        name: [0.0, 0.0]
        for name in (
            "nominal_elevation_deg",
            "elevation_correction_deg",
            "azimuth_correction_deg",
            "vertical_offset_m",
            "horizontal_offset_m",
            "range_offset_m",
        )
    }
    d = {"schema_version": 1, "lidar_intrinsics": {**beams, "range_scale": [1.0, 1.0]}}
    assert CalibrationResult.from_dict(d).lidar_intrinsics.num_beams == 2
    d["lidar_intrinsics"]["range_scale"] = [1.0]
    with pytest.raises(
        FileValueError, match=r"`lidar_intrinsics\.range_scale` is \[1\.0\], not a list of 2"
    ):
        CalibrationResult.from_dict(d)
    del d["lidar_intrinsics"]["range_scale"]
    with pytest.raises(FileValueError, match=r"`lidar_intrinsics\.range_scale` is missing"):
        CalibrationResult.from_dict(d)


@pytest.mark.parametrize("block", ["extrinsic", "imu_intrinsics"])
def test_a_rotations_readable_twin_is_checked_beside_its_quaternion(block: str) -> None:
    prefix = "rotation" if block == "extrinsic" else "gyro_rotation"
    d = {"schema_version": 1, block: {f"{prefix}_quaternion": [0, 0, 0, 1]}}
    CalibrationResult.from_dict(d)
    d[block][f"{prefix}_rpy_deg"] = "level"
    with pytest.raises(FileValueError, match=rf"`{block}\.{prefix}_rpy_deg` is 'level'"):
        CalibrationResult.from_dict(d)
