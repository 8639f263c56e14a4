"""The sample buffer on its own (no ROS)."""

import threading

import numpy as np
import pytest

from spm_sysid.core.stream.buffer import SampleBuffer


def test_pairs_identical_stamps_in_order():
    b = SampleBuffer(10)
    for k in range(5):
        assert b.add_input(k * 100, float(k))
        assert b.add_output(k * 100, -float(k))
    st, u, y = b.snapshot()
    assert st.tolist() == [0, 100, 200, 300, 400]
    assert u.tolist() == [0, 1, 2, 3, 4] and y.tolist() == [0, -1, -2, -3, -4]
    assert b.stats.paired == 5 and b.stats.pending_inputs == 0


def test_tolerance_and_unpaired_samples_are_counted():
    b = SampleBuffer(10, tolerance_ns=10)
    b.add_input(0, 1.0)
    b.add_output(5, 2.0)        # within 10 ns: paired
    b.add_input(100, 3.0)
    b.add_output(150, 4.0)      # 50 ns away: no pair; input 100 can never pair now
    b.add_input(152, 5.0)       # pairs with output 150
    s = b.stats
    assert len(b) == 2 and s.unpaired_inputs == 1 and s.unpaired_outputs == 0
    assert b.snapshot()[1].tolist() == [1.0, 5.0]


def test_nonfinite_and_out_of_order_are_rejected_and_counted():
    b = SampleBuffer(10)
    assert not b.add_input(0, float("nan"))
    assert not b.add_output(0, float("inf"))
    assert b.add_input(10, 1.0)
    assert not b.add_input(5, 2.0)    # older than the last input
    assert not b.add_input(10, 2.0)   # same stamp again
    assert b.stats.held_out_of_order == 2  # held: could be the start of a jump back
    assert b.add_output(10, 3.0)
    assert b.add_input(20, 4.0)       # in order again: the two late samples were outliers
    s = b.stats
    assert s.rejected_nonfinite == 2 and s.rejected_out_of_order == 2
    assert s.held_out_of_order == 0 and s.time_jumps == 0
    assert len(b) == 1 and s.received_inputs == 5 and s.received_outputs == 2


def test_full_buffer_drops_the_oldest_and_counts_them():
    b = SampleBuffer(3)
    for k in range(7):
        b.add_input(k, float(k))
        b.add_output(k, float(k))
    st, u, _ = b.snapshot()
    assert st.tolist() == [4, 5, 6] and u.tolist() == [4.0, 5.0, 6.0]
    assert b.stats.dropped_oldest == 4 and b.stats.samples == 3


def test_pending_is_bounded():
    b = SampleBuffer(10, max_pending=5)
    for k in range(8):
        b.add_input(k, 1.0)
    assert b.stats.pending_inputs == 5 and b.stats.unpaired_inputs == 3


def test_clear_and_snapshot_is_a_copy():
    b = SampleBuffer(10)
    b.add_input(1, 1.0)
    b.add_output(1, 2.0)
    st, u, y = b.snapshot()
    u[0] = 99.0
    assert b.snapshot()[1][0] == 1.0
    assert b.clear() == 1 and len(b) == 0 and b.stats.cleared == 1
    b.add_input(0, 1.0)  # stamps may restart after a clear
    b.add_output(0, 1.0)
    assert len(b) == 1


def test_concurrent_writers_and_snapshots_lose_nothing():
    n = 20_000
    # one writer may run far ahead of the other: let every sample wait for its partner
    b = SampleBuffer(100_000, max_pending=n)

    def writer(add):
        for k in range(n):
            add(k * 1000, float(k))

    threads = [threading.Thread(target=writer, args=(b.add_input,)),
               threading.Thread(target=writer, args=(b.add_output,))]
    for t in threads:
        t.start()
    sizes = []
    while any(t.is_alive() for t in threads):
        st, u, y = b.snapshot()
        assert np.array_equal(u, y)  # every snapshot is consistent
        sizes.append(len(st))
    for t in threads:
        t.join()
    assert len(b) == n and b.stats.unpaired_inputs + b.stats.unpaired_outputs == 0
    assert sizes == sorted(sizes)


def test_invalid_buffer_settings():
    with pytest.raises(ValueError):
        SampleBuffer(0)
    with pytest.raises(ValueError):
        SampleBuffer(10, tolerance_ns=-1)


def test_far_future_stamp_costs_one_sample_and_recovers_by_itself():
    b = SampleBuffer(1000, resync_samples=5)
    for k in range(10):
        b.add_input(k * 10, float(k))
        b.add_output(k * 10, float(k))
    b.add_input(10**15, 99.0)           # one input stamped far in the future
    for k in range(10, 40):
        b.add_input(k * 10, float(k))
        b.add_output(k * 10, float(k))
    st, u, y = b.snapshot()
    s = b.stats
    assert s.time_jumps == 1 and s.discarded_on_jump == 1
    assert u.tolist() == [float(k) for k in range(40)] == y.tolist()  # nothing else lost
    assert s.pending_inputs == s.pending_outputs == s.held_out_of_order == 0
    assert s.rejected_out_of_order == 0 and s.unpaired_outputs == 0


def test_replayed_timeline_becomes_a_new_segment():
    from spm_sysid.core.model.segments import find_segments

    b = SampleBuffer(1000)
    for rep in range(2):               # the same 50 stamps twice, as a replayed bag
        for k in range(50):
            b.add_input(k * 10, float(k + 100 * rep))
            b.add_output(k * 10, float(k + 100 * rep))
    st, u, _ = b.snapshot()
    assert len(u) == 100 and b.stats.time_jumps == 2  # each stream jumped once
    info = find_segments(st)
    assert info.bounds == [(0, 50), (50, 100)] and info.restarts == 1 and info.gaps == 0


def test_several_input_streams_align_with_the_output():
    # stream 0 carries two inputs (e.g. two joint efforts), stream 1 one more
    b = SampleBuffer(100, tolerance_ns=5, input_widths=(2, 1))
    for k in range(6):
        b.add_input(k * 100, (k, 10 * k), stream=0)
        b.add_output(k * 100 + 2, -k)
    for k in range(6):  # the second input topic lags behind: nothing is lost meanwhile
        if k != 3:      # ... and loses one message: that sample cannot be aligned
            b.add_input(k * 100 + 4, 100 * k, stream=1)
    st, u, y = b.snapshot()
    assert u.shape == (5, 3)
    assert u.tolist() == [[k, 10 * k, 100 * k] for k in (0, 1, 2, 4, 5)]
    assert y.tolist() == [0, -1, -2, -4, -5]
    assert st.tolist() == [4, 104, 204, 404, 504]  # the latest stamp of each sample
    s = b.stats
    assert s.unpaired_inputs == 1 and s.unpaired_outputs == 1  # sample 3's others
    assert s.received_inputs == 11 and s.pending_inputs == s.pending_outputs == 0


def test_a_stream_of_the_wrong_width_is_an_error():
    b = SampleBuffer(10, input_widths=(2,))
    with pytest.raises(ValueError, match="carries 2 value"):
        b.add_input(0, 1.0)
    with pytest.raises(ValueError, match="input_widths"):
        SampleBuffer(10, input_widths=())
