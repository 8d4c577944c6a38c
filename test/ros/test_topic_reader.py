"""Readers outside the executor (`damon_ros.ros.topic_reader`): in order, on arrival, closable."""

from __future__ import annotations

import threading
import time

import rosutil
from std_msgs.msg import Int32

from damon_ros.ros.topic_reader import Inbox, TopicReader


def test_reader_hands_over_every_message_in_order_and_sleeps_between():
    with rosutil.RosClient(rosutil.next_domain_id(__file__)) as ros:
        got, drained = [], []
        reader = TopicReader(ros.node, Int32, "numbers", lambda m: got.append(m.data),
                             suffix="numbers", qos=100,
                             on_drained=lambda: drained.append(len(got)))
        pub = ros.publisher(Int32, "numbers", 100)
        try:
            assert ros.wait_for_subscribers(pub, 1, 20.0)
            for i in range(50):
                pub.publish(Int32(data=i))
            assert ros.spin_until(lambda: len(got) == 50, 20.0), got
            assert got == list(range(50))
            assert drained and drained[-1] == 50  # on_drained after each batch
            batches = len(drained)
            ros.spin_for(0.3)  # nothing new: no further batch, however long it waits
            assert len(drained) == batches
        finally:
            t0 = time.monotonic()
            reader.close()
            assert time.monotonic() - t0 < 1.5  # its wait is interrupted, not timed out


def test_inbox_wait_returns_on_interrupt_and_keeps_only_its_depth():
    with rosutil.RosClient(rosutil.next_domain_id(__file__)) as ros:
        inbox = Inbox(ros.node, Int32, "latest", "latest", qos=1)
        pub = ros.publisher(Int32, "latest", 10)
        try:
            assert ros.wait_for_subscribers(pub, 1, 20.0)
            threading.Timer(0.2, inbox.interrupt).start()
            t0 = time.monotonic()
            inbox.wait(10.0)
            assert time.monotonic() - t0 < 5.0  # woken by the interrupt, not the timeout
            for i in range(5):
                pub.publish(Int32(data=i))
            time.sleep(1.0)
            takes: list[list[int]] = []
            ros.spin_until(lambda: takes.append([t.msg.data for t in inbox.take_all()])
                           or 4 in takes[-1], 20.0)
            assert takes[-1] == [4]  # the newest arrives
            assert all(len(t) <= 1 for t in takes)  # depth 1: never a backlog
        finally:
            inbox.close()
