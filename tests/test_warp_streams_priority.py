"""Which CUDA stream priority each kind of GPU work asks for (`streams.PRIORITIES`): the
driver's numbers are checked on the GPU host (tests/test_warp_batch.py)."""

from __future__ import annotations

import pytest

pytest.importorskip("warp", reason="needs warp-lang (the [test] extra has it)")

from vabench.sim_mjx.warp import streams


@pytest.mark.parametrize(
    ("least", "greatest", "middle"),
    [(0, -5, -3), (0, -2, -1), (0, -1, -1), (0, 0, 0), (3, -3, 0)],
)
def test_the_middle_priority_lies_between_the_render_passes_and_the_critical_path(
    least, greatest, middle
):
    assert streams.priority_value("least", least, greatest) == least
    assert streams.priority_value("greatest", least, greatest) == greatest
    value = streams.priority_value("middle", least, greatest)
    assert value == middle
    assert greatest <= value <= least
    if least - greatest >= 2:  # room for a level of its own
        assert greatest < value < least


def test_an_unknown_priority_is_refused_on_every_device():
    import warp as wp

    with pytest.raises(ValueError, match="least"):
        streams.priority_value("high", 0, -5)
    with pytest.raises(ValueError, match="middle"):
        streams.new_stream(wp.get_device("cpu"), "urgent")
    assert streams.new_stream(wp.get_device("cpu"), "middle") is None
