"""The unplanned-fault watch of system tests: a link drop nobody injected is reported,
one inside ``injected_faults`` is the test's own (fxcell.testing.faults)."""

from __future__ import annotations

import logging

from fxcell.testing import injected_faults
from fxcell.testing.faults import watching

LINK_LOG = logging.getLogger("fxcell.link.client")


def _drop(reason: str) -> None:
    LINK_LOG.warning("robot link to %s down: %s", "127.0.0.9", reason)


def test_a_link_drop_nobody_injected_is_reported() -> None:
    with watching([]) as watch:
        _drop("no robot state for 104 ms")
        assert watch.unplanned() == ["link down: no robot state for 104 ms"]


def test_a_link_drop_inside_injected_faults_is_the_tests_own() -> None:
    with watching([]) as watch:
        with injected_faults("the link process killed", link_losses=1):
            _drop("link process exited")
        assert watch.unplanned() == []
        assert watch.injected == ["link down: link process exited"]
        _drop("link process exited")  # after the block: unplanned again
        assert watch.unplanned() == ["link down: link process exited"]


def test_a_drop_before_the_block_stays_unplanned() -> None:
    with watching([]) as watch:
        _drop("first")
        with injected_faults("a stall"):
            _drop("second")
        assert watch.unplanned() == ["link down: first"]


def test_other_warnings_are_not_faults() -> None:
    with watching([]) as watch:
        LINK_LOG.warning("robot state stream gap of %.0f ms", 36.0)
        assert watch.unplanned() == []


def test_a_step_the_cell_healed_is_a_fault() -> None:
    # a move that lost its robot state while the link stayed up (a Ned2's WebSocket stream
    # stalled) is healed without any "link down": the heal itself is counted
    heal = logging.getLogger("fxcell.cell.healing")
    with watching([]) as watch:
        heal.warning(
            "%s interrupted (%s): recovering, attempt %d",
            "rise from tray A1",
            "no robot state for 1 s during a move",
            1,
        )
        heal.warning("%s done after recovering (attempt %d)", "rise from tray A1", 1)
        assert watch.unplanned() == ["link healed: no robot state for 1 s during a move"]


def test_a_move_the_link_braked_by_itself_is_a_fault() -> None:
    with watching([]) as watch:
        LINK_LOG.warning("robot link to %s braked a move by itself: %s", "127.0.0.9", "cell_silent")
        assert watch.unplanned() == ["link braked a move by itself: cell_silent"]
