"""Fixtures of the real-data tests (defined in ``real_data.py``)."""

from real_data import ouster_arrays, ouster_bags  # noqa: F401
