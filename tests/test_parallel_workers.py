"""On parallel workers a test that loads the machine itself (``@pytest.mark.alone``) holds
the machine's test lock exclusively, and the gate in front of it, and every other test holds it
shared (tests/conftest.py): checked from inside each kind of test. In one process the lock is
not taken at all."""

from __future__ import annotations

import fcntl
import os
from pathlib import Path

import pytest
from conftest import MACHINE_GATE, MACHINE_LOCK

on_workers = pytest.mark.skipif(
    "PYTEST_XDIST_WORKER" not in os.environ, reason="the lock is taken on parallel workers only"
)


def _can_lock(kind: int, path: Path = MACHINE_LOCK) -> bool:
    """Whether a lock of ``kind`` on the machine's test lock (or its gate) is free right now
    (a second open file: flock conflicts with this process's own lock on the first)."""
    with open(path, "a+") as other:
        try:
            fcntl.flock(other, kind | fcntl.LOCK_NB)
        except BlockingIOError:
            return False
        fcntl.flock(other, fcntl.LOCK_UN)
        return True


@on_workers
def test_an_ordinary_test_shares_the_machine() -> None:
    assert not _can_lock(fcntl.LOCK_EX)  # its own shared lock keeps an alone test out
    assert _can_lock(fcntl.LOCK_SH)  # another ordinary test may run beside it


@on_workers
@pytest.mark.alone
def test_an_alone_test_has_the_machine_to_itself() -> None:
    assert not _can_lock(fcntl.LOCK_SH)  # no other test can start beside it
    assert not _can_lock(fcntl.LOCK_SH, MACHINE_GATE)  # nor wait in front of it


@pytest.fixture(scope="module")
def shared() -> object:
    return object()


@on_workers
def test_a_test_sharing_a_module_fixture_runs_in_its_files_work_unit(
    shared: object, request: pytest.FixtureRequest
) -> None:
    # pytest-xdist's loadgroup names the unit in the node id its worker runs
    assert request.node.nodeid.endswith("@tests/test_parallel_workers.py")
