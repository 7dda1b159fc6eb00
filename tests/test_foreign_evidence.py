"""The second-master watch's quick answer (``ForeignTraffic.evidence``: nothing came since, so
nothing to build, asked for every drive every supervisor period) is the full answer for any
traffic: every kind of frame it reports moves its ``newest`` mark (generated frames, the full
answer computed beside it)."""

from __future__ import annotations

import time

import can
from hypothesis import given, settings
from hypothesis import strategies as st

from motor_driver.bus.traffic import ForeignTraffic

HOST, NODES = 0x7F, (1, 2, 3)

frames = st.one_of(
    st.builds(lambda: can.Message(arbitration_id=0x080, data=b"", is_extended_id=False)),  # SYNC
    st.builds(lambda cmd, node: can.Message(arbitration_id=0x000, data=bytes([cmd, node]), is_extended_id=False),
              st.sampled_from([0x01, 0x02, 0x80, 0x81, 0x82]), st.sampled_from([0, *NODES, 9])),  # NMT
    st.builds(lambda: can.Message(arbitration_id=0x700 + HOST, data=b"\x05", is_extended_id=False)),  # host twin
    st.builds(lambda node, cs: can.Message(arbitration_id=0x600 + node, data=bytes([cs, 0x40, 0x60, 0, 0, 0, 0, 0]),
                                           is_extended_id=False),
              st.sampled_from([*NODES, 9]), st.sampled_from([0x23, 0x2B, 0x2F, 0x40])),  # SDO write / read
    st.builds(lambda cob, data: can.Message(arbitration_id=cob, data=data, is_extended_id=False),
              st.integers(0x001, 0x7FF), st.binary(max_size=8)),  # anything
)


@settings(max_examples=300, deadline=None)
@given(st.lists(frames, min_size=1, max_size=40), st.sampled_from([0.0, 0.01]))
def test_the_quick_answer_is_the_full_answer(traffic: list[can.Message], own_sync_period_s: float) -> None:
    watch = ForeignTraffic(HOST, NODES)
    watch.own_sync_period_s = own_sync_period_s
    start = time.monotonic() - 1.0
    for msg in traffic:
        before = time.monotonic()
        watch.on_message_received(msg)
        for node in (*NODES, 9):
            for since in (start, before):
                assert watch.evidence(node, since) == watch._evidence(node, since), (msg, node)
    assert watch.evidence(1, time.monotonic()) == ""  # nothing after now
