"""Image messages' fields decode to the tracker's arrays, and colour/depth frames pair by stamp.

Both are what the tracker node does before any perception (damon_ros.ros.images): plain
message fields in, so no ROS graph is needed to check them.
"""

from __future__ import annotations

import numpy as np
import pytest

from damon_ros.ros.images import FrameSynchronizer, decode_color, decode_depth


def test_decode_images_from_message_fields():
    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 256, (4, 5, 3), dtype=np.uint8)
    padded = np.zeros((4, 16), np.uint8)
    padded[:, :15] = rgb.reshape(4, 15)
    assert np.array_equal(decode_color("rgb8", 4, 5, 16, padded.tobytes()), rgb)
    bgr = rgb[..., ::-1].copy()
    assert np.array_equal(decode_color("bgr8", 4, 5, 15, bgr.tobytes()), rgb)
    depth = rng.integers(0, 5000, (4, 5), dtype=np.uint16)
    assert np.array_equal(decode_depth("16UC1", 4, 5, 10, depth.astype("<u2").tobytes()), depth)
    big = decode_depth("16UC1", 4, 5, 10, depth.astype(">u2").tobytes(), is_bigendian=True)
    assert np.array_equal(big, depth)
    metres = (depth / 1000.0).astype("<f4")
    metres[0, 0] = np.nan
    out = decode_depth("32FC1", 4, 5, 20, metres.tobytes())
    assert out[0, 0] == 0 and np.array_equal(out.ravel()[1:], depth.ravel()[1:])
    with pytest.raises(ValueError, match="encoding 'mono8' is not supported"):
        decode_color("mono8", 4, 5, 15, bgr.tobytes())
    with pytest.raises(ValueError, match="encoding '8UC1' is not supported"):
        decode_depth("8UC1", 4, 5, 5, bytes(20))
    with pytest.raises(ValueError, match="less than height\\*step"):
        decode_color("rgb8", 4, 5, 15, bytes(10))
    with pytest.raises(ValueError, match="step 8 is less than"):
        decode_depth("16UC1", 4, 5, 8, bytes(40))



# --- colour/depth synchronisation ----------------------------------------------------------


def test_synchroniser_pairs_in_order_frames_exactly():
    sync = FrameSynchronizer()
    pairs = []
    for i in range(5):
        t = i / 30
        assert sync.add_color(t, f"c{i}") == []
        pairs += sync.add_depth(t, f"d{i}")
    assert [(p.color, p.depth) for p in pairs] == [(f"c{i}", f"d{i}") for i in range(5)]
    assert [p.stamp for p in pairs] == [i / 30 for i in range(5)]
    assert sync.pending() == (0, 0) and sync.dropped == 0


def test_synchroniser_pairs_within_tolerance_only():
    sync = FrameSynchronizer(tolerance_s=0.005)
    sync.add_color(1.000, "c")
    (pair,) = sync.add_depth(1.004, "d")
    assert pair == (1.000, "c", "d")
    sync.add_color(2.000, "c2")
    assert sync.add_depth(2.010, "d2") == []
    assert sync.pending() == (1, 1)


def test_synchroniser_handles_out_of_order_arrival():
    sync = FrameSynchronizer(tolerance_s=0.002)
    stamps = [0.0, 1 / 30, 2 / 30, 3 / 30]
    pairs = []
    # Depth runs ahead, and colour frames 1 and 2 arrive swapped.
    for t in stamps:
        pairs += sync.add_depth(t + 0.001, f"d{t:.3f}")
    for t in (stamps[0], stamps[2], stamps[1], stamps[3]):
        pairs += sync.add_color(t, f"c{t:.3f}")
    got = [(p.color, p.depth) for p in pairs]
    # Frame 1 arrived after frame 2 had been paired: too late for a tracker, dropped.
    assert got == [("c0.000", "d0.000"), ("c0.067", "d0.067"), ("c0.100", "d0.100")]
    assert [p.stamp for p in pairs] == sorted(p.stamp for p in pairs)
    assert sync.pending() == (0, 0) and sync.dropped == 2  # d0.033 pruned, c0.033 late
    # A repeated frame of the last pair's stamp is no new information either.
    assert sync.add_color(stamps[3], "again") == [] and sync.add_depth(stamps[3], "again") == []
    assert sync.pending() == (0, 0) and sync.dropped == 4


def test_synchroniser_survives_dropped_frames_and_bounds_its_queues():
    sync = FrameSynchronizer(queue_size=3)
    pairs = []
    for i in range(20):
        t = i / 30
        pairs += sync.add_color(t, i)
        if i % 4 != 1:  # every fourth depth frame is lost
            pairs += sync.add_depth(t, i)
    assert [p.color for p in pairs] == [i for i in range(20) if i % 4 != 1]
    assert sync.pending() == (0, 0)
    for i in range(10):  # the depth stream dies: the colour queue stays bounded
        sync.add_color(1.0 + i / 30, i)
    assert sync.pending() == (3, 0)
    (pair,) = sync.add_depth(1.0 + 9 / 30, "late")
    assert pair.color == 9


def test_synchroniser_rejects_bad_arguments():
    with pytest.raises(ValueError, match="tolerance_s"):
        FrameSynchronizer(tolerance_s=-1.0)
    with pytest.raises(ValueError, match="queue_size"):
        FrameSynchronizer(queue_size=0)
    with pytest.raises(ValueError, match="not finite"):
        FrameSynchronizer().add_color(float("inf"), None)
