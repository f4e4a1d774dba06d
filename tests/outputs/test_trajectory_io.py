"""TUM / KITTI trajectory files: strict parsing, exact round trips, atomic incremental writing."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pvslam_core.outputs.trajectory_io import (
    TrajectoryFormatError,
    TrajectoryWriter,
    read_kitti_poses,
    read_tum,
    write_kitti,
    write_tum,
)


def random_poses(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    q = Rotation.random(n, random_state=seed).as_quat()
    return np.concatenate([rng.normal(0, 5, (n, 3)), q], axis=1)


def test_tum_round_trip_exact(tmp_path):
    ts = 1305031102.175304 + np.cumsum(np.random.default_rng(1).uniform(0.01, 0.1, 40))
    poses = random_poses(40)
    p = tmp_path / "traj.txt"
    write_tum(p, ts, poses)
    ts2, poses2 = read_tum(p)
    assert ts2.dtype == np.float64 and poses2.shape == (40, 7)
    np.testing.assert_array_equal(ts2, ts)
    np.testing.assert_array_equal(poses2, poses)
    # No temporary files left behind.
    assert sorted(os.listdir(tmp_path)) == ["traj.txt"]


def test_tum_accepts_torch(tmp_path):
    torch = pytest.importorskip("torch")
    poses = torch.tensor(random_poses(3))
    write_tum(tmp_path / "t.txt", torch.tensor([0.0, 1.0, 2.0], dtype=torch.float64), poses)
    _, p = read_tum(tmp_path / "t.txt")
    np.testing.assert_array_equal(p, poses.numpy())


def test_tum_comments_blank_lines(tmp_path):
    p = tmp_path / "t.txt"
    p.write_text("# header\n\n0.0 1 2 3 0 0 0 1\n   \n# mid\n0.5 1 2 3 0 0 0 1  # trailing comment\n")
    ts, poses = read_tum(p)
    np.testing.assert_array_equal(ts, [0.0, 0.5])
    assert poses.shape == (2, 7)


def test_tum_empty_file(tmp_path):
    p = tmp_path / "t.txt"
    p.write_text("# nothing\n")
    ts, poses = read_tum(p)
    assert ts.shape == (0,) and poses.shape == (0, 7)


@pytest.mark.parametrize(
    "body, line, words",
    [
        ("0 1 2 3 0 0 0 1\n1 1 2 3 0 0 1\n", 2, "expected 8"),
        ("0 1 2 3 0 0 0 1\n1 1 2 x 0 0 0 1\n", 2, "not a number"),
        ("# c\n0 1 2 3 0 0 0 1\n1 1 2 3 0 0 0 1\n1 1 2 3 0 0 0 1\n", 4, "duplicate"),
        ("0 1 2 3 0 0 0 1\n2 1 2 3 0 0 0 1\n1 1 2 3 0 0 0 1\n", 3, "unsorted"),
        ("0 1 2 3 0 0 0 0\n", 1, "zero quaternion"),
        ("0 1 2 nan 0 0 0 1\n", 1, "non-finite"),
    ],
)
def test_tum_errors_name_file_and_line(tmp_path, body, line, words):
    p = tmp_path / "bad.txt"
    p.write_text(body)
    with pytest.raises(TrajectoryFormatError) as ei:
        read_tum(p)
    msg = str(ei.value)
    assert f"{p}:{line}" in msg and words in msg


def test_tum_missing_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="missing.txt"):
        read_tum(tmp_path / "missing.txt")


def test_write_tum_rejects_bad_input(tmp_path):
    with pytest.raises(ValueError, match="strictly increasing"):
        write_tum(tmp_path / "t.txt", [0.0, 0.0], random_poses(2))
    with pytest.raises(ValueError, match="not finite"):
        bad = random_poses(2)
        bad[1, 0] = np.nan
        write_tum(tmp_path / "t.txt", [0.0, 1.0], bad)
    with pytest.raises(ValueError, match=r"\[N, 7\]"):
        write_tum(tmp_path / "t.txt", [0.0], np.zeros((1, 6)))
    assert not os.listdir(tmp_path)


def test_kitti_round_trip(tmp_path):
    poses = random_poses(25, seed=3)
    p = tmp_path / "k.txt"
    write_kitti(p, poses)
    rows = np.loadtxt(p)
    assert rows.shape == (25, 12)
    back = read_kitti_poses(p)
    np.testing.assert_allclose(back[:, :3], poses[:, :3], atol=1e-12)
    # Same rotation (q and -q are the same rotation).
    dots = np.abs(np.sum(back[:, 3:] * poses[:, 3:], axis=1))
    np.testing.assert_allclose(dots, 1.0, atol=1e-12)
    # Matrix is T_wc: t is the camera centre, R the camera-to-world rotation.
    m = rows[0].reshape(3, 4)
    np.testing.assert_allclose(m[:, :3], Rotation.from_quat(poses[0, 3:]).as_matrix(), atol=1e-12)


def test_kitti_real_file(shared_dir):
    KITTI_POSES = shared_dir / "data" / "kitti-odometry" / "poses" / "06.txt"
    poses = read_kitti_poses(KITTI_POSES)
    raw = np.loadtxt(KITTI_POSES).reshape(-1, 3, 4)
    assert poses.shape == (51, 7)
    np.testing.assert_allclose(poses[:, :3], raw[:, :, 3])
    np.testing.assert_allclose(Rotation.from_quat(poses[:, 3:]).as_matrix(), raw[:, :, :3], atol=1e-5)


def test_kitti_errors(tmp_path):
    p = tmp_path / "k.txt"
    p.write_text("1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0 0 0 1 0 0 0 0 1\n")
    with pytest.raises(TrajectoryFormatError, match=rf"{p}:2.*expected 12"):
        read_kitti_poses(p)


# ---------------------------------------------------------------------------------------------------------------
# TrajectoryWriter
# ---------------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("fmt", ["tum", "kitti"])
def test_writer_append_update_flush(tmp_path, fmt):
    p = tmp_path / "traj.txt"
    poses = random_poses(10)
    w = TrajectoryWriter(p, fmt=fmt)
    for i in range(5):
        w.append(0.1 * i, poses[i])
    w.flush()
    # "Killed" here: the file holds the 5 flushed poses.
    read = (lambda: read_tum(p)[1]) if fmt == "tum" else (lambda: read_kitti_poses(p))
    got = read()
    assert len(got) == 5
    np.testing.assert_allclose(got[:, :3], poses[:5, :3], atol=1e-12)
    # More appends without a flush do not touch the file.
    w.append(0.5, poses[5])
    assert len(read()) == 5
    # BA changed past poses: replace everything.
    new = random_poses(6, seed=9)
    w.update(0.1 * np.arange(6), new)
    w.flush()
    got = read()
    assert len(got) == 6
    np.testing.assert_allclose(got[:, :3], new[:, :3], atol=1e-12)
    assert [f for f in os.listdir(tmp_path)] == ["traj.txt"]


def test_writer_rejects_bad_appends_without_corrupting(tmp_path):
    p = tmp_path / "traj.txt"
    w = TrajectoryWriter(p)
    w.append(0.0, random_poses(1)[0])
    with pytest.raises(ValueError, match="not after"):
        w.append(0.0, random_poses(1)[0])
    with pytest.raises(ValueError):
        w.append(1.0, np.full(7, np.nan))
    with pytest.raises(ValueError):
        w.update([0.0, 0.0], random_poses(2))
    assert len(w) == 1
    w.flush()
    assert len(read_tum(p)[0]) == 1


def test_writer_exception_in_with_block_keeps_valid_file(tmp_path):
    p = tmp_path / "traj.txt"
    poses = random_poses(8)
    with pytest.raises(RuntimeError, match="boom"):
        with TrajectoryWriter(p) as w:
            for i in range(4):
                w.append(float(i), poses[i])
            w.flush()
            flushed = read_tum(p)
            w.append(4.0, poses[4])
            raise RuntimeError("boom")
    ts, got = read_tum(p)
    # The last flushed content is intact (a prefix), and what the run had at the error was saved.
    np.testing.assert_array_equal(ts[:4], flushed[0])
    np.testing.assert_array_equal(got[:4], flushed[1])
    np.testing.assert_array_equal(ts, [0.0, 1.0, 2.0, 3.0, 4.0])
    np.testing.assert_array_equal(got, poses[:5])


def test_writer_exception_during_flush_keeps_previous_file(tmp_path, monkeypatch):
    p = tmp_path / "traj.txt"
    w = TrajectoryWriter(p)
    w.append(0.0, random_poses(1)[0])
    w.flush()
    before = p.read_text()
    w.append(1.0, random_poses(1)[0])
    import pvslam_core.outputs.trajectory_io as tio

    def failing(ts, poses):
        raise OSError("disk full")

    monkeypatch.setattr(tio, "_tum_text", lambda ts, poses: "partial garbage" + failing(ts, poses))
    with pytest.raises(OSError):
        w.flush()
    assert p.read_text() == before
    assert os.listdir(tmp_path) == ["traj.txt"]


def test_writer_survives_sigkill_between_updates(tmp_path):
    """A process killed at any moment leaves a complete, readable trajectory file."""
    p = tmp_path / "traj.txt"
    marker = tmp_path / "ready"
    code = textwrap.dedent(
        f"""
        import numpy as np, os, time
        from pvslam_core.outputs.trajectory_io import TrajectoryWriter
        w = TrajectoryWriter({str(p)!r}, flush_every=1)
        rng = np.random.default_rng(0)
        i = 0
        while True:
            q = rng.normal(size=4); q /= np.linalg.norm(q)
            w.append(float(i), np.concatenate([rng.normal(size=3), q]))
            if i % 7 == 0:
                w.update(w.timestamps, w.poses + np.array([1e-3, 0, 0, 0, 0, 0, 0]))
            if i == 50:
                open({str(marker)!r}, "w").close()
            i += 1
        """
    )
    import pvslam_core

    root = os.path.dirname(os.path.dirname(os.path.abspath(pvslam_core.__file__)))
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([root] + sys.path))
    proc = subprocess.Popen([sys.executable, "-c", code], env=env)
    try:
        import time

        t0 = time.time()
        while not marker.exists():
            assert proc.poll() is None, "writer process died"
            assert time.time() - t0 < 60
            time.sleep(0.01)
        time.sleep(0.2)
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    ts, poses = read_tum(p)
    assert len(ts) >= 50
    np.testing.assert_array_equal(ts, np.arange(len(ts), dtype=float))


from hypothesis import given, settings, strategies as st  # noqa: E402
from hypothesis.extra.numpy import arrays  # noqa: E402


@settings(max_examples=30, deadline=None)
@given(
    n=st.integers(1, 20),
    t0=st.floats(-1e9, 1e10, allow_nan=False),
    vals=arrays(np.float64, (20, 7), elements=st.floats(-1e6, 1e6, allow_nan=False, allow_subnormal=True)),
)
def test_tum_round_trip_property(tmp_path_factory, n, t0, vals):
    ts = t0 + np.arange(n) * max(1e-3, abs(t0) * 1e-12)
    poses = vals[:n].copy()
    poses[:, 6] += 2e6  # quaternion never zero
    p = tmp_path_factory.mktemp("rt") / "t.txt"
    write_tum(p, ts, poses)
    ts2, poses2 = read_tum(p)
    np.testing.assert_array_equal(ts2, ts)
    np.testing.assert_array_equal(poses2, poses)


def test_tum_with_bom(tmp_path):
    p = tmp_path / "bom.txt"
    p.write_bytes(b"\xef\xbb\xbf0.0 1 2 3 0 0 0 1\n")
    assert read_tum(p)[0].tolist() == [0.0]
