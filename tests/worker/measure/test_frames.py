"""worker.measure.frames: the frame-by-frame prefetch gives each group's stack, in order."""

from types import SimpleNamespace

import numpy as np
import pytest

from worker.measure.frames import prefetch


class _Bundle:
    """Frames are ints; frame f's radiance is the constant f (and 13 is unreadable)."""

    manifest = SimpleNamespace(camera=SimpleNamespace(height=3, width=2))

    def radiance(self, frame, *, out=None):
        if frame == 13:
            raise ValueError("frame 13 is broken")
        if out is None:
            return np.full((3, 2), frame, np.float32)
        out[...] = frame
        return out


@pytest.mark.parametrize(("workers", "ahead"), [(1, 0), (2, 1), (3, 2), (2, 10)])
def test_groups_come_back_in_order_whatever_the_threads(workers, ahead):
    groups = [[0, 1, 2, 3], [4], [5, 6], [7, 8, 9, 10, 11, 12]]
    stacks = list(prefetch(_Bundle(), groups, workers=workers, ahead=ahead))
    assert len(stacks) == len(groups)
    for stack, group in zip(stacks, groups, strict=True):
        assert stack.shape == (len(group), 3, 2) and stack.dtype == np.float32
        np.testing.assert_array_equal(stack[:, 0, 0], group)


@pytest.mark.parametrize(("workers", "ahead"), [(1, 0), (3, 2)])
def test_reused_buffers_hold_each_group_while_the_caller_has_it(workers, ahead):
    groups = [[0, 1], [2, 3], [4], [5, 6], [7, 8], [9, 10], [11, 12]]
    seen, buffers = [], set()
    for stack, group in zip(
        prefetch(_Bundle(), groups, workers=workers, ahead=ahead, reuse=True), groups, strict=True
    ):
        np.testing.assert_array_equal(stack[:, 0, 0], group)
        seen.append(stack.copy())
        buffers.add(id(stack))
    assert [s[:, 0, 0].tolist() for s in seen] == groups
    # Two-frame groups share at most ahead + 2 buffers (the caller's and those ahead).
    assert len(buffers) <= ahead + 3


def test_a_frame_that_cannot_be_decoded_fails_its_group():
    stacks = prefetch(_Bundle(), [[11, 12], [13, 14]], workers=2)
    np.testing.assert_array_equal(next(stacks)[:, 1, 1], [11, 12])
    with pytest.raises(ValueError, match="frame 13"):
        next(stacks)
