"""inference.frames.FrameLoader: frames decoded ahead on a pool give exactly the batch
preprocessing, each prefetched frame is decoded once (the overlap too), and a video is read
one frame at a time."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

pytest.importorskip("cv2")


def _frames(n, hw=(60, 90)):
    rng = np.random.default_rng(0)
    return [rng.integers(0, 255, (*hw, 3), np.uint8) for _ in range(n)]


@pytest.mark.parametrize("mode", ["crop", "pad"])
def test_loader_equals_the_batch_preprocessing(mode):
    from inference.frames import FrameLoader
    from inference.preprocess import preprocess

    frames = _frames(7)
    loader = FrameLoader(lambda k: frames[k], lambda imgs: preprocess(imgs, mode=mode), threads=3)
    try:
        loader.prefetch([0, 1, 2, 3, 4])
        loader.prefetch([3, 4, 5, 6])  # the overlap is scheduled twice
        first, second = loader.load([0, 1, 2, 3, 4]), loader.load([3, 4, 5, 6])
    finally:
        loader.close()
    np.testing.assert_array_equal(first, preprocess(frames[:5], mode=mode))
    np.testing.assert_array_equal(second, preprocess(frames[3:], mode=mode))


def test_each_prefetched_frame_is_decoded_once_and_kept_until_taken():
    from inference.frames import FrameLoader

    reads = []
    loader = FrameLoader(
        lambda k: reads.append(k) or np.full((2, 2, 3), k, np.uint8),
        lambda imgs: np.stack([i.transpose(2, 0, 1) for i in imgs]).astype(np.float32),
        threads=2,
    )
    try:
        loader.prefetch([0, 1, 2])
        loader.prefetch([2, 3])
        assert loader.load([0, 1, 2])[:, 0, 0, 0].tolist() == [0, 1, 2]
        assert loader.load([2, 3])[:, 0, 0, 0].tolist() == [2, 3]
        assert sorted(reads) == [0, 1, 2, 3]  # frame 2 (both chunks) decoded once
        loader.load([2])  # nothing scheduled: decoded again, on demand
        assert sorted(reads) == [0, 1, 2, 2, 3]
    finally:
        loader.close()


def test_a_video_is_read_one_frame_at_a_time():
    from inference.frames import FrameLoader

    inside, most = [0], [0]
    lock = threading.Lock()

    def read(k):
        with lock:
            inside[0] += 1
            most[0] = max(most[0], inside[0])
        time.sleep(0.01)
        with lock:
            inside[0] -= 1
        return np.zeros((2, 2, 3), np.uint8)

    loader = FrameLoader(read, lambda imgs: np.zeros((len(imgs), 3, 2, 2), np.float32), threads=4, serial_reads=True)
    try:
        loader.load(range(8))
    finally:
        loader.close()
    assert most[0] == 1
