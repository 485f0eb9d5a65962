"""Map files: binary PLY and PCD with intensity, beam and time per point, read back with
Open3D; written atomically."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from licalib_cli.errors import ConfigError
from licalib_cli.io.map_writer import write_map

o3d = pytest.importorskip("open3d")


def _chunks(n: int, parts: int) -> list[SimpleNamespace]:
    rng = np.random.default_rng(1)
    out = []
    for k in range(parts):
        out.append(
            SimpleNamespace(
                xyz=rng.uniform(-20, 20, (n, 3)),
                beam=rng.integers(0, 128, n).astype(np.uint16),
                time_s=k + np.sort(rng.uniform(0, 1, n)),
                intensity=rng.uniform(0, 255, n).astype(np.float32),
            )
        )
    return out


@pytest.mark.parametrize("suffix", [".ply", ".pcd", ".PLY"])
def test_map_reads_back_in_open3d(tmp_path, suffix):
    chunks = _chunks(500, 3)
    path = tmp_path / f"map{suffix}"
    assert write_map(path, 1500, chunks) == 1500
    cloud = o3d.t.io.read_point_cloud(str(path))
    xyz = np.concatenate([c.xyz for c in chunks])
    np.testing.assert_allclose(cloud.point["positions"].numpy(), xyz, atol=1e-5, rtol=1e-6)
    np.testing.assert_array_equal(
        cloud.point["beam"].numpy().ravel(), np.concatenate([c.beam for c in chunks])
    )
    np.testing.assert_array_equal(
        cloud.point["time"].numpy().ravel(), np.concatenate([c.time_s for c in chunks])
    )
    np.testing.assert_array_equal(
        cloud.point["intensity"].numpy().ravel(), np.concatenate([c.intensity for c in chunks])
    )
    # The legacy reader (what most Open3D scripts use) sees the points too.
    assert len(o3d.io.read_point_cloud(str(path)).points) == 1500
    assert [p.name for p in tmp_path.iterdir()] == [path.name]


def test_a_failed_write_leaves_no_file(tmp_path):
    path = tmp_path / "map.ply"
    with pytest.raises(ValueError, match="announced 10 points"):
        write_map(path, 10, _chunks(5, 1))
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(ConfigError, match=r"\.ply or \.pcd"):
        write_map(tmp_path / "map.las", 5, _chunks(5, 1))
    assert list(tmp_path.iterdir()) == []
