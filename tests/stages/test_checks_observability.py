"""An extrinsic direction the data do not determine: the finding says what would determine it.

With the gyro-to-IMU rotation or the accelerometer's misalignment estimated, the rotation that
turns the accelerometer's frame against the gyro and the LiDAR is seen by the accelerometer alone
(gravity from different attitudes). A shaken rig that hardly tilts leaves it undetermined
although it rotated about all three axes, so "record with rotation about more axes" does not
help there.
"""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from licalib_cli.estimation import CALIBRATION_SCALES
from licalib_cli.pipeline.checks import (
    _observability,
    accelerometer_frame_advice,
    accelerometer_frame_partners,
)
from licalib_cli.residuals import (
    ACCEL_MISALIGNMENT,
    EXT_ROTATION,
    EXT_TRANSLATION,
    GYRO_ROTATION,
    TIME_OFFSET,
)
from licalib_cli.solver.lm import NOT_OBSERVABLE_WEIGHT, SolverReport
from licalib_cli.solver.observability import describe_direction

EXT = [f"{EXT_ROTATION}.r{a}" for a in "xyz"] + [f"{EXT_TRANSLATION}.{a}" for a in "xyz"]
EXT = [*EXT, TIME_OFFSET]
GYRO = [f"{GYRO_ROTATION}.r{a}" for a in "xyz"]
MISALIGNMENT = [f"{ACCEL_MISALIGNMENT}.{a}" for a in ("xy", "xz", "yz")]
TZ = f"{EXT_TRANSLATION}.z"
TILT = {
    f"{EXT_ROTATION}.rx": -0.17e-3,
    f"{EXT_ROTATION}.ry": 0.98e-3,
    f"{EXT_ROTATION}.rz": -0.07e-3,
}
"""The extrinsic rotation's part of seed 809's truncated direction, rad (LiDAR frame)."""


def _scale(names: list[str]) -> np.ndarray:
    """The solver's characteristic scale of each coordinate (one per block here)."""
    block = {n: n if n == TIME_OFFSET else n.rsplit(".", 1)[0] for n in names}
    return np.array([CALIBRATION_SCALES[block[n]][0] for n in names], dtype=np.float64)


def _report(moved: dict[str, float], names: list[str]) -> Any:
    """A report with one truncated direction, ``moved`` in the coordinates' own units (rad, m);
    the coordinates it touches reported not observable (the solver's
    :data:`~licalib_cli.solver.lm.NOT_OBSERVABLE_WEIGHT` rule)."""
    scale = _scale(names)
    physical = np.array([moved.get(n, 0.0) for n in names])
    vector = physical / scale  # the truncation works in scaled coordinates
    direction = describe_direction(vector, names, verdict="not determined by the data")
    observable = direction.vector**2 < NOT_OBSERVABLE_WEIGHT
    fields: dict[str, Any] = {f: None for f in SolverReport.__dataclass_fields__}
    fields.update(
        calibration_names=tuple(names),
        information=SimpleNamespace(scale=scale, owners=tuple(n.rsplit(".", 1)[0] for n in names)),
        truncated=(direction,),
        observable=observable,
        weak=(),
    )
    return SolverReport(**fields)


def test_the_accelerometer_frame_is_named_though_the_text_shows_only_the_extrinsic() -> None:
    """The diagnose benchmark's seed 809 (OS1-64 shake, 10 s): its truncated direction held
    0.99 mrad of gyro-to-IMU rotation per 1.00 mrad of extrinsic rotation (and 0.3 mm of t_z);
    in scaled coordinates the gyro's share is 1 %, so the direction's text names the extrinsic
    rotation alone."""
    moved = {**TILT, f"{GYRO_ROTATION}.rx": 0.25e-3, f"{GYRO_ROTATION}.ry": -0.96e-3, TZ: -3e-4}
    report = _report(moved, EXT + GYRO)
    (direction,) = report.truncated
    assert GYRO_ROTATION not in direction.text  # what the user would see without the check
    assert accelerometer_frame_partners(report, direction) == (GYRO_ROTATION,)
    findings = _observability(report, {})
    assert findings and all(f.information for f in findings)
    texts = [f.text for f in findings]
    advice = accelerometer_frame_advice((GYRO_ROTATION,))
    assert advice in texts
    assert "the gyro-to-IMU rotation estimated (gyro_rotation)" in advice
    assert "leave gyro_rotation out of the model (model.imu)" in advice
    assert "licalib select-segments with this model ranks the windows" in advice
    assert not any("rotation about more axes" in t for t in texts)
    assert not any("rotation about all three axes" in t for t in texts)
    (first,) = (t for t in texts if t.startswith("The data determine only"))
    assert "trades off with the gyro-to-IMU rotation (below)" in first


def test_the_accelerometers_misalignment_turns_its_frame_too() -> None:
    """Trust bag 4456 (20 s VLP-16 shake, every intrinsic estimated): the truncated direction
    held the accelerometer's misalignment [0.80, -0.09, 0.01] with the extrinsic rotation [0.31,
    0.50, -0.05] (mrad both) and a WARN told the user to rotate about more axes."""
    moved = {
        f"{ACCEL_MISALIGNMENT}.xy": 0.80e-3,
        f"{ACCEL_MISALIGNMENT}.xz": -0.09e-3,
        f"{ACCEL_MISALIGNMENT}.yz": 0.01e-3,
        f"{EXT_ROTATION}.rx": 0.31e-3,
        f"{EXT_ROTATION}.ry": 0.50e-3,
        f"{EXT_ROTATION}.rz": -0.05e-3,
    }
    report = _report(moved, EXT + GYRO + MISALIGNMENT)
    (direction,) = report.truncated
    assert accelerometer_frame_partners(report, direction) == (ACCEL_MISALIGNMENT,)
    texts = [f.text for f in _observability(report, {})]
    advice = accelerometer_frame_advice((ACCEL_MISALIGNMENT,))
    assert advice in texts
    assert "the accelerometer's misalignment estimated (accel_misalignment)" in advice
    assert not any("rotation about more axes" in t for t in texts)
    both = accelerometer_frame_advice((GYRO_ROTATION, ACCEL_MISALIGNMENT))
    assert (
        "(gyro_rotation and accel_misalignment), the extrinsic rotation trades off with them"
        in (both)
    )


@pytest.mark.parametrize(
    ("moved", "names"),
    [
        # the extrinsic rotation alone: the motion's fault
        ({**TILT, TZ: -3e-4}, EXT + GYRO + MISALIGNMENT),
        # a gyro-to-IMU part far smaller than the extrinsic one
        ({**TILT, f"{GYRO_ROTATION}.ry": -0.2e-3, TZ: -3e-4}, EXT + GYRO),
        # neither block estimated
        ({**TILT, TZ: -3e-4}, EXT),
    ],
)
def test_other_directions_keep_the_advice_on_motion(
    moved: dict[str, float], names: list[str]
) -> None:
    report = _report(moved, names)
    (direction,) = report.truncated
    assert accelerometer_frame_partners(report, direction) == ()
    texts = [f.text for f in _observability(report, {})]
    assert not any(t.startswith("With the") for t in texts)
    assert any("rotation about more axes" in t for t in texts)
    assert any("rotation about all three axes" in t for t in texts)


def test_the_joint_verdict_of_segments_gives_the_same_advice() -> None:
    """``--segments``: the segments' joint problem shares the extrinsic and the intrinsics, so a
    direction it leaves undetermined is told apart the same way."""
    from licalib_cli.pipeline.joint import joint_truncation_reasons

    moved = {**TILT, f"{GYRO_ROTATION}.rx": 0.25e-3, f"{GYRO_ROTATION}.ry": -0.96e-3, TZ: -3e-4}
    report = _report(moved, EXT + GYRO)
    (direction,) = report.truncated
    reasons = joint_truncation_reasons(report)
    assert reasons == [
        f"Not observable from the segments together: {direction.text}",
        f"Segments together: {accelerometer_frame_advice((GYRO_ROTATION,))}",
    ]
    # the extrinsic alone: listed, no advice on tilting
    alone = joint_truncation_reasons(_report({**TILT, TZ: -3e-4}, EXT + GYRO))
    assert len(alone) == 1 and alone[0].startswith("Not observable from the segments together")
    # a truncated direction that leaves the extrinsic alone is not a reason
    gyro_only = {f"{GYRO_ROTATION}.rx": 1e-3}
    assert joint_truncation_reasons(_report(gyro_only, EXT + GYRO)) == []


def test_a_weakly_determined_extrinsic_direction_warns_and_is_listed() -> None:
    """Below the threshold but estimated (``LMParams.weak_floor``): the coordinates keep their
    sigmas (no FAIL for undetermined coordinates), the verdict warns with the direction and the
    same advice on what would determine it, and the result lists it apart from the truncated."""
    from dataclasses import replace

    from licalib_cli.pipeline.checks import observability_of

    moved = {**TILT, f"{GYRO_ROTATION}.rx": 0.25e-3, f"{GYRO_ROTATION}.ry": -0.96e-3, TZ: -3e-4}
    truncated = _report(moved, EXT + GYRO)
    (direction,) = truncated.truncated
    report = replace(
        truncated,
        truncated=(),
        weak=(direction,),
        observable=np.ones(len(EXT + GYRO), dtype=bool),
        tsvd_threshold=1.0,
        scaling="s",
        singular_values=np.ones(len(EXT + GYRO)),
        weak_floor=0.2,
    )
    found = _observability(report, {})
    assert [f.severity for f in found] == ["warn", "warn"]
    assert found[0].text == (
        f"Weakly determined by this data: {direction.text}; its sigmas rest on little information."
    )
    assert found[1].text == accelerometer_frame_advice((GYRO_ROTATION,))
    assert not any("determine only" in f.text for f in found)
    section = observability_of(report)
    assert section.weakly_determined == (direction.text,) and section.unobservable == ()
    assert section.weak_floor == 0.2  # the rule the solver applied, for the report
    # the truncated direction alone: not observable, and a FAIL for the undetermined extrinsic
    assert any(f.severity == "fail" for f in _observability(truncated, {}))
