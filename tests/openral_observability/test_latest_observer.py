"""LatestPerKeyObserver: the newest item per key wins, nothing blocks the offering thread, close drains."""

from __future__ import annotations

import threading

from openral_observability.latest_observer import LatestPerKeyObserver


class _Gated(LatestPerKeyObserver[str, int]):
    """Records what it handles; the first item blocks until released, so offers pile up behind it."""

    def __init__(self) -> None:
        super().__init__(name="test-latest")
        self.seen: list[tuple[str, int]] = []
        self.entered = threading.Event()
        self.release = threading.Event()
        self.closes = 0

    def handle_item(self, key: str, item: int) -> None:
        self.entered.set()
        assert self.release.wait(10)
        if item < 0:
            raise RuntimeError("bad item")
        self.seen.append((key, item))

    def handle_close(self) -> None:
        self.closes += 1


def test_newer_items_replace_waiting_ones_per_key_and_close_drains() -> None:
    observer = _Gated()
    observer.start()
    observer.offer("cam", 1)
    assert observer.entered.wait(10)  # the worker holds item 1; everything below waits behind it
    for value in range(2, 6):
        observer.offer("cam", value)
    observer.offer("wrist", 7)
    assert observer.pending == 2
    assert observer.replaced == 3
    observer.release.set()
    observer.close()
    assert observer.seen == [("cam", 1), ("cam", 5), ("wrist", 7)]
    assert observer.handled == 3
    assert observer.closes == 1
    observer.close()
    assert observer.closes == 1, "a second close does nothing"


def test_a_failing_item_is_counted_and_the_worker_goes_on() -> None:
    observer = _Gated()
    observer.release.set()
    observer.start()
    observer.offer("cam", -1)
    observer.offer("wrist", 2)
    observer.close()
    assert observer.errors == 1
    assert ("wrist", 2) in observer.seen


def test_restart_after_close_and_offers_before_start_are_kept() -> None:
    observer = _Gated()
    observer.release.set()
    observer.offer("cam", 1)  # before start: waits for the worker
    observer.start()
    observer.close()
    observer.start()
    observer.offer("cam", 2)
    observer.close()
    assert observer.seen == [("cam", 1), ("cam", 2)]


def test_close_without_start_still_handles_what_was_offered() -> None:
    observer = _Gated()
    observer.release.set()
    observer.offer("cam", 3)
    observer.close()
    assert observer.seen == [("cam", 3)]
    assert observer.closes == 1
