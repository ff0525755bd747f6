"""The ``--reload`` watcher's thread (``container._watch``) on real files: what it delivers, and when."""

from __future__ import annotations

import logging
import threading
from pathlib import Path

import pytest

from container._watch import Batch, _snapshot, _touched, _unseen, _watch


class Deliveries:
    """What the watching thread delivers, to wait on."""

    def __init__(self) -> None:
        self.batches: list[Batch] = []
        self._changed = threading.Condition()

    def __call__(self, batch: Batch) -> None:
        with self._changed:
            self.batches.append(batch)
            self._changed.notify_all()

    def first_change(self, timeout: float = 5.0) -> Batch:
        with self._changed:
            assert self._changed.wait_for(lambda: any(self.batches), timeout), "no change delivered"
            return next(batch for batch in self.batches if batch)


def _start(root: Path, before: dict[str, tuple[int, int]]) -> tuple[threading.Event, Deliveries, threading.Thread]:
    stop, deliveries = threading.Event(), Deliveries()
    thread = threading.Thread(target=_watch, args=([root], before, stop, deliveries), daemon=True)
    thread.start()
    return stop, deliveries, thread


def test_a_change_saved_before_the_watch_is_in_place_is_delivered(tmp_path: Path) -> None:
    source = tmp_path / "plugin.py"
    source.write_text("A = 1\n", encoding="utf-8")
    before = _snapshot([tmp_path])
    source.write_text("A = 22\n", encoding="utf-8")  # between deciding to watch and watching

    stop, deliveries, thread = _start(tmp_path, before)
    try:
        batch = deliveries.first_change()
    finally:
        stop.set()
        thread.join(5.0)

    assert {path for _, path in batch} == {str(source)}


def test_a_burst_of_saves_is_one_batch_and_byte_code_is_left_out(tmp_path: Path) -> None:
    source = tmp_path / "plugin.py"
    source.write_text("A = 1\n", encoding="utf-8")
    (tmp_path / "__pycache__").mkdir()
    stop, deliveries, thread = _start(tmp_path, _snapshot([tmp_path]))
    try:
        for value in range(5):
            source.write_text(f"A = {value}\n", encoding="utf-8")
        (tmp_path / "__pycache__" / "plugin.cpython-312.pyc").write_bytes(b"\0")
        (tmp_path / ".plugin.py.swp").write_bytes(b"\0")
        batch = deliveries.first_change()
    finally:
        stop.set()
        thread.join(5.0)

    assert {path for _, path in batch} == {str(source)}
    assert [batch for batch in deliveries.batches if batch] == [batch]


def test_changes_are_told_to_the_distributions_whose_files_they_are(tmp_path: Path) -> None:
    sources = {"a-nodes": [tmp_path / "a_nodes"], "b-nodes": [tmp_path / "b_nodes.py"]}
    modified = object()

    assert _touched({(modified, str(tmp_path / "a_nodes" / "sub" / "x.py"))}, sources) == ["a-nodes"]
    assert _touched({(modified, str(tmp_path / "b_nodes.py"))}, sources) == ["b-nodes"]
    assert _touched({(modified, str(tmp_path / "a_nodes_extra" / "x.py"))}, sources) == []


def test_a_watch_that_fails_says_so(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    gone = tmp_path / "removed"

    with caplog.at_level(logging.ERROR, logger="container.reload"):
        _watch([gone], {}, threading.Event(), Deliveries())  # returns: nothing to watch

    assert f"Reloading on change stopped: watching [{gone!r}] failed: FileNotFoundError" in caplog.text, caplog.text


def test_a_saved_state_is_told_once_however_many_ways_it_is_seen(tmp_path: Path) -> None:
    """The first comparison and the OS watch can both tell one save (a reload failing twice for it):
    each state of a file is delivered once."""
    source = tmp_path / "plugin.py"
    source.write_text("A = 1\n", encoding="utf-8")
    known = _snapshot([tmp_path])
    source.write_text("A = 22\n", encoding="utf-8")

    assert _unseen([str(source)], known) == {str(source)}  # found by comparing
    assert _unseen([str(source)], known) == set()  # then told by the OS watch: the same state
    source.write_text("A = 333\n", encoding="utf-8")
    assert _unseen([str(source)], known) == {str(source)}
    source.unlink()
    assert _unseen([str(source)], known) == {str(source)}
    assert _unseen([str(source)], known) == set()
