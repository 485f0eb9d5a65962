"""How the command line prints the unobservable directions of a calibration."""

from __future__ import annotations

from licalib_cli.commands.render import unobservable_lines

_VERDICT = "unobservable, not estimated (stays near its initial value)"


def _beam_direction(beam: int, coord: str) -> str:
    return (
        f"lidar.intrinsics (lidar.intrinsics[{beam}].{coord} +0.71, "
        f"lidar.intrinsics[{beam + 1}].{coord} -0.70): {_VERDICT}"
    )


def test_few_directions_are_printed_as_they_are() -> None:
    texts = [
        f"ext.translation along [0.00, 0.00, 1.00] in the IMU frame: {_VERDICT}",
        _beam_direction(3, "s"),
    ]
    assert unobservable_lines(texts) == texts


def test_many_intrinsic_directions_are_counted_by_their_leading_coordinate() -> None:
    extrinsic = (
        "ext.translation along [0.00, 0.00, 1.00] in the IMU frame + lidar.intrinsics "
        f"(lidar.intrinsics[2].V +0.30): {_VERDICT}"
    )
    texts = [
        *(_beam_direction(b, "s") for b in range(5)),
        extrinsic,
        _beam_direction(9, "drho"),
        f"imu.gyro_scale along [1.00, 0.00, 0.00]: {_VERDICT}",
    ]
    lines = unobservable_lines(texts)
    # the direction that moves the extrinsic stays in full, first; the others become one line
    assert lines[0] == extrinsic
    assert len(lines) == 2
    assert lines[1].startswith(
        "7 directions of the intrinsics alone (5 by range scale, 1 by range offset, "
        "1 by IMU intrinsics) stay at their initial values"
    )
