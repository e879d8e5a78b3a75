"""``serve.testing.send_files`` sends the next C-STORE of an association only once pynetdicom's reactor has resumed
from the previous request's pause (otherwise, on a starved CPU, the reactor can take the next response for an
unexpected message and the request times out)."""

from __future__ import annotations

import threading
import time
from types import SimpleNamespace

from monai_rigidreg.serve.testing import _wait_for_reactor


def test_waits_until_the_reactor_has_resumed():
    assoc = SimpleNamespace(_is_paused=True, is_established=True)
    threading.Timer(0.2, lambda: setattr(assoc, "_is_paused", False)).start()
    t = time.monotonic()
    _wait_for_reactor(assoc)
    assert 0.15 < time.monotonic() - t < 5 and assoc._is_paused is False


def test_does_not_wait_on_a_running_reactor_an_ended_association_or_forever():
    t = time.monotonic()
    _wait_for_reactor(SimpleNamespace(_is_paused=False, is_established=True))
    _wait_for_reactor(SimpleNamespace(_is_paused=True, is_established=False))
    assert time.monotonic() - t < 0.1
    t = time.monotonic()
    _wait_for_reactor(SimpleNamespace(_is_paused=True, is_established=True), seconds=0.3)
    assert 0.25 < time.monotonic() - t < 2
