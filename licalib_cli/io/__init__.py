"""Bag input/output: the only package that imports rosbags."""
