"""ROS 1 bags whose bag order is not the publisher's: scans come back in header.seq order.

The shared intel.bag was written in stamp order from a log with a bursty clock: 1,612 scans are
stored out of their sequence, and only header.seq keeps the order the CARMEN log has.
"""

from __future__ import annotations

import dataclasses

import pytest
from frslam_graph.datasets import open_recording
from frslam_graph.datasets.rosbag import in_seq_order
from test_rosbag import LASER, Msgs, read_all, write_bag


def scan_with_seq(m: Msgs, seq: int, stamp: float, value: float):
    msg = m.scan(stamp, [value] * 4)
    return dataclasses.replace(msg, header=dataclasses.replace(msg.header, seq=seq))


def test_scans_stored_out_of_seq_order_come_back_in_it(tmp_path):
    m = Msgs(True)
    # taken in seq order 0..4 with a bursty clock: stamps 1.0, 2.0, 1.5, 3.0, 2.9; the bag
    # was written in stamp order
    taken = [(0, 1.0), (1, 2.0), (2, 1.5), (3, 3.0), (4, 2.9)]
    stored = sorted(taken, key=lambda st: st[1])
    msgs = [("/scan", LASER, t, scan_with_seq(m, seq, t, 1.0 + seq)) for seq, t in stored]
    bag = write_bag(tmp_path / "seq.bag", msgs)
    scans, warns = read_all(open_recording(bag))
    assert [s.stamp for s in scans] == [t for _seq, t in taken]
    assert [s.ranges[0] for s in scans] == pytest.approx([1.0, 2.0, 3.0, 4.0, 5.0])
    assert "2 scans stored out of header.seq order (yielded in seq order)" in warns[0]
    assert "2 scans stamped before an earlier scan (kept in header.seq order)" in warns[0]
    skipped, _ = read_all(open_recording(bag, backwards="skip"))
    assert [s.stamp for s in skipped] == [1.0, 2.0, 3.0]


class _H:
    def __init__(self, seq):
        self.seq = seq


class _M:
    def __init__(self, seq):
        self.header = _H(seq)


def order(seqs, window=4):
    items = [("/scan", "t", i, _M(s)) for i, s in enumerate(seqs)]
    return [(moved, item[2]) for moved, item in in_seq_order(iter(items), window)]


def test_equal_seqs_and_restarts_keep_the_bag_order():
    assert order([0, 0, 0, 0, 0, 0]) == [(False, i) for i in range(6)]
    # a publisher restarted: seq falls back by more than the window, a new run starts
    assert [i for _m, i in order([10, 11, 12, 13, 14, 15, 0, 1, 2])] == list(range(9))
    # within the window: sorted; the message that came earlier in the bag is the moved one
    assert order([0, 2, 1, 3]) == [(False, 0), (False, 2), (True, 1), (False, 3)]
