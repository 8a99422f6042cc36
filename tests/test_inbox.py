"""The bounded hand-over from Zenoh's threads to a service's loop, on a real Zenoh session."""

import time

import pytest
from netutil import free_port, wait_for

from topseg.services.runtime.inbox import Inbox
from topseg.services.runtime.zenoh_session import open_session


def test_an_inbox_keeps_order_drops_and_counts_when_full_and_drains():
    with open_session(None, free_port()) as session:
        inbox = Inbox(3, stamp=True)
        sub = session.declare_subscriber("t/inbox/**", inbox.on_sample)
        pub = session.declare_publisher("t/inbox/a")
        for i in range(5):
            pub.put(bytes([i]))
        wait_for(lambda: inbox.dropped == 2, what="the two messages beyond the bound dropped")
        key, payload, stamp = inbox.get(1.0)
        assert (key, payload) == ("t/inbox/a", b"\x00")
        assert abs(stamp - time.time_ns()) < 60e9
        assert [item[1] for item in inbox.drain()] == [b"\x01", b"\x02"]
        assert inbox.get(0.01) is None  # empty: a timeout
        inbox.wake()
        t0 = time.monotonic()
        assert inbox.get(30.0) is None  # woken at once, not after the timeout
        assert time.monotonic() - t0 < 10.0
        sub.undeclare()


def test_an_unstamped_inbox_holds_key_and_payload():
    with open_session(None, free_port()) as session:
        inbox = Inbox(8)
        session.declare_subscriber("t/plain", inbox.on_sample)
        session.put("t/plain", b"abc")
        got = []
        wait_for(lambda: got.extend(inbox.drain()) or got, what="the message")
        assert got == [("t/plain", b"abc")] and inbox.dropped == 0


def test_an_inbox_holds_at_least_one_message():
    with pytest.raises(ValueError, match="at least one"):
        Inbox(0)
