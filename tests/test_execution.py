"""The execution policy of batched simulations (`jaxmotion._sim.execution`): padding to lane
groups, chunking, and one compiled size per call shape."""

from jaxmotion._sim import execution


def test_device_shares_are_whole_lane_groups_and_never_a_large_power_of_two():
    """A device's share covers its controllers in whole groups of 8 lanes (at least 16), and
    steps past the powers of two from 64 up, whose strides thrash the cache."""
    for n in range(1, 2100):
        share = execution.share(n)
        assert share >= max(n, 16) and share % 8 == 0
        assert share - max(n, 16) < 16, (n, share)  # at most the lanes and one group extra
        if share >= 64:
            assert share & (share - 1) != 0, (n, share)
    assert [execution.share(n) for n in (1, 16, 17, 50, 64, 250, 256, 500)] == [
        16,
        16,
        24,
        56,
        72,
        264,
        264,
        504,
    ]
