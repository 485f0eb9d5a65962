"""Rotation and rigid-transform math (pure numpy, no I/O). See :mod:`licalib_cli.geometry.so3`."""

from __future__ import annotations

from licalib_cli.geometry import so3

__all__ = ["so3"]
