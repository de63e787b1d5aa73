"""When ``haptic-topology run`` takes the run as recorded (``GraphWatcher.recorder_has_the_run``,
on the nodes' own ``/diagnostics`` counts), without a ROS graph: the watcher's statuses set by
hand."""

from __future__ import annotations

from haptic_topology.bringup.watch import RECORDER_STATUS, SETTLE_REPORTS, GraphWatcher
from haptic_topology.vocabulary import TOPIC_HAND_INPUTS, TOPIC_VT_PATH


def _watcher(ve_batches: int, ve_last: int, ve_lost: int) -> GraphWatcher:
    w = GraphWatcher.__new__(GraphWatcher)      # no rclpy: only the status logic
    rec = {f'received {TOPIC_HAND_INPUTS}': '500', f'received {TOPIC_VT_PATH}': '4000'}
    w.status = {
        'device_driver: loop': {'loop_running': 'false', 'seq': '5000'},
        'lmi_controller: loop': {'hand_pending': '0', 'hand_last_seq': '5000',
                                 f'sent {TOPIC_HAND_INPUTS}': '500'},
        've_sim: loop': {f'received {TOPIC_HAND_INPUTS}': str(ve_batches),
                         'hand_last_seq': str(ve_last), 'lost_hand_inputs': str(ve_lost),
                         'path_pending': '0', f'sent {TOPIC_VT_PATH}': '4000'},
        RECORDER_STATUS: rec}
    w._recorder_counts = [dict(rec)] * SETTLE_REPORTS     # settled (wall clock)
    return w


def test_the_run_ends_once_the_ve_took_the_last_input_even_if_dds_dropped_some() -> None:
    assert _watcher(500, 5000, 0).recorder_has_the_run(False)
    # A starved VE whose reliable queue overflowed: 30 batches never came (lost, counted);
    # it took the last one, so the run is complete (it would otherwise wait for ever).
    assert _watcher(470, 5000, 300).recorder_has_the_run(False)
    # The last batch is still on its way: not yet.
    assert not _watcher(499, 4990, 0).recorder_has_the_run(False)


def test_a_rejected_hand_input_batch_ends_the_run_with_its_reason() -> None:
    """The VE never takes a batch it rejected, so the VE's last seq never reaches the
    controller's and the end of the run would wait in vain: ``run`` ends on the VE's report
    instead, in one line naming the count and the first reason (as ve_sim words it)."""
    w = _watcher(400, 4000, 0)
    assert w.hand_inputs_rejected() is None           # a VE that rejected nothing
    # ... or only refused another sender's well-formed batches (the admission's ``session``,
    # ``continuity``, ``source``): the run goes on without them.
    w.status['ve_sim: loop'].update({'rejected_messages': '7', 'rejected_hand_batches': '0',
                                     'hand_rejection': ''})
    assert w.hand_inputs_rejected() is None
    assert not w.recorder_has_the_run(False)          # ... waits: the VE is behind
    first = ('HandInputs.coupling_wrench must be within +-1000, got [11.5, 1000.17, -3.97, '
             '-0.09, 0.07, 0.33] (sample 3) (at 10.907 s of the run)')
    w.status['ve_sim: loop'].update({'rejected_messages': '98', 'rejected_hand_batches': '91',
                                     'hand_rejection': first})
    assert w.hand_inputs_rejected() == (
        've_sim rejected 91 hand input batches (the first: HandInputs.coupling_wrench must be '
        'within +-1000, got [11.5, 1000.17, -3.97, -0.09, 0.07, 0.33] (sample 3) (at 10.907 s '
        'of the run)); the VE did not take their inputs, so the run was stopped')
    w.status['ve_sim: loop']['rejected_hand_batches'] = '1'
    assert str(w.hand_inputs_rejected()).startswith('ve_sim rejected 1 hand input batch (the '
                                                    'first: HandInputs.coupling_wrench')
