"""The controller's hand inputs for the VE, in batches of one VE update period.

``ve_sim`` integrates every hand input (eq. 2, zero-order hold between them) but publishes an
LMI update only every ``update_period`` inputs (10 at 1 kHz: 100 Hz). So the inputs need not
travel one message per device cycle: :class:`HandBatcher` collects the
:class:`~haptic_topology.control.loop.HandSample` of each answered cycle and hands out a
:class:`HandBatch` (one ``HandInputs`` message) when the sample's ``seq`` is a multiple of the
period, the same schedule the VE's updates follow. In lock-step the batch that completes a
period therefore reaches the VE at exactly the step where the offline simulation takes its
update (:meth:`~haptic_topology.control.loop.ControllerLoop.waiting_for_update`).

Why: a reliable 1 kHz stream with seconds of history over UDP turned every gap (the VE
stopped for 1 s, or restarted) into a repair burst that overflowed the socket buffer again,
and it never recovered; ten samples per message is a tenth of the datagrams, repairs and
acknowledgements.

Samples must not wait for a period that may never complete (the last cycles of a run, the
cycles before the device stalls): :meth:`HandBatcher.due`, called by a steady-clock timer,
hands out the pending samples once the oldest is ``max_age`` seconds old (about two periods).
Such a partial batch changes nothing the VE computes: it takes the samples one by one, as
single inputs, and counts its update period in samples, not in messages.

No clock and no rclpy: ``now`` is the caller's steady time (s). Buffers are allocated once;
:meth:`HandBatcher.add` (1 kHz) only writes a row.

Example::

    >>> import numpy as np
    >>> from haptic_topology.control.loop import HandSample
    >>> z = np.zeros(3)
    >>> b = HandBatcher(period=10, dim=3, max_age=0.02)
    >>> out = [b.add(HandSample(k, 100 + k, 0.0, z, z, z, z, z), k * 1_000_000, 0.001 * k)
    ...        for k in range(1, 13)]
    >>> [len(x) for x in out if x is not None], b.pending
    ([10], 2)
    >>> b.due(0.020) is None, len(b.due(0.032)), b.pending
    (True, 2, 0)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from haptic_topology.control.loop import HandSample


@dataclass(frozen=True)
class HandBatch:
    """n hand inputs, oldest first: the controller's ``seq`` (from 1), ``state_seq`` (loop
    seq of the device state), ``stamp_ns`` (that state's stamp, integer ns, so the message
    carries it exactly), and n x m ``pose``, ``twist``, ``hand_wrench`` (F_h), ``coupling``
    (F_pc); layouts as ``DeviceState``."""

    seq: np.ndarray
    state_seq: np.ndarray
    stamp_ns: np.ndarray
    pose: np.ndarray
    twist: np.ndarray
    hand_wrench: np.ndarray
    coupling: np.ndarray

    def __len__(self) -> int:
        return int(self.seq.size)


class HandBatcher:
    """Collects hand samples into batches of ``period`` (see module doc); ``dim``: the task
    dimension m; ``max_age``: age (s, steady clock) of the oldest pending sample from which
    :meth:`due` hands out a partial batch."""

    def __init__(self, period: int, dim: int, max_age: float) -> None:
        if period < 1:
            raise ValueError(f'period must be >= 1, got {period}')
        if not max_age > 0.0:
            raise ValueError(f'max_age must be > 0 s, got {max_age}')
        self.period = period
        self.dim = dim
        self.max_age = max_age
        self._ints = np.zeros((3, period), dtype=np.int64)   # seq, state_seq, stamp_ns
        self._rows = np.zeros((4, period, dim))              # pose, twist, F_h, F_pc
        self._n = 0
        self._since = 0.0
        #: Batches handed out, and how many of them were partial (by :meth:`due`/:meth:`flush`).
        self.batches = 0
        self.partial = 0
        #: ``seq`` of the newest sample added (0: none yet)
        self.last_seq = 0

    @property
    def pending(self) -> int:
        """Samples added and not handed out yet."""
        return self._n

    def add(self, sample: HandSample, stamp_ns: int, now: float) -> HandBatch | None:
        """Append ``sample`` (its state's stamp ``stamp_ns``, steady time ``now``); return the
        batch to publish when ``sample.seq`` completes a period, else None."""
        i = self._begin(sample.seq, sample.state_seq, stamp_ns, now)
        rows = self._rows
        rows[0, i] = sample.pose
        rows[1, i] = sample.twist
        rows[2, i] = sample.hand_wrench
        rows[3, i] = sample.coupling
        return self._end(sample.seq)

    def add_block(self, seq: int, state_seq: int, stamp_ns: int, block: np.ndarray,
                  now: float) -> HandBatch | None:
        """:meth:`add` of the sample ``seq`` of loop state ``state_seq`` whose ``pose``,
        ``twist``, ``hand_wrench`` and ``coupling`` are the rows of the 4 x m ``block``."""
        self._rows[:, self._begin(seq, state_seq, stamp_ns, now)] = block
        return self._end(seq)

    def _begin(self, seq: int, state_seq: int, stamp_ns: int, now: float) -> int:
        """The row of a new sample, its integers written."""
        i = self._n
        if i == 0:
            self._since = now
        self._ints[:, i] = (seq, state_seq, stamp_ns)
        self.last_seq = seq
        return i

    def _end(self, seq: int) -> HandBatch | None:
        """The sample ``seq`` written: the batch it completes, or None."""
        self._n += 1
        if seq % self.period == 0 or self._n == self.period:
            return self._take(partial=False)
        return None

    def due(self, now: float) -> HandBatch | None:
        """The pending samples if the oldest is at least ``max_age`` old at ``now``."""
        if self._n and now - self._since >= self.max_age:
            return self._take(partial=True)
        return None

    def flush(self) -> HandBatch | None:
        """The pending samples, whatever their age (None: nothing pending)."""
        return self._take(partial=True) if self._n else None

    def _take(self, partial: bool) -> HandBatch:
        n = self._n
        self._n = 0
        self.batches += 1
        self.partial += int(partial)
        ints, rows = self._ints[:, :n].copy(), self._rows[:, :n].copy()
        return HandBatch(ints[0], ints[1], ints[2], rows[0], rows[1], rows[2], rows[3])
