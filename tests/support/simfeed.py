"""Simulated sessions for the viewer's tests: a sim run (:mod:`hippomap.sim`) as mapper inputs.

:func:`sim_inputs` turns a :class:`hippomap.sim.SimRun` into the time-ordered inputs a robot would
send: one :class:`~hippomap.inputs.Odometry` per step (velocities held since the previous step,
the run's causal convention, with the step's ground-truth pose as ``gt``) and, after the steps
that have a camera frame, that
:class:`~hippomap.inputs.Frame` (rendered on demand) a millisecond later, so every input's time
strictly follows the previous one.
"""

from __future__ import annotations

from typing import Iterator

from hippomap.inputs import Frame, Odometry

FRAME_DELAY_S = 1e-3


def sim_inputs(run, start: int = 0, stop: int | None = None) -> Iterator[Odometry | Frame]:
    """Inputs of odometry steps ``start:stop`` of ``run`` (a ``hippomap.sim.SimRun``), in time order."""
    frame_of = {int(s): i for i, s in enumerate(run.frame_steps)}
    stop = len(run) if stop is None else min(stop, len(run))
    for k in range(start, stop):
        t, v, w = (float(x) for x in run.odometry[k])
        yield Odometry(t=t, v=v, omega=w, gt=tuple(float(x) for x in run.groundtruth[k]))
        i = frame_of.get(k)
        if i is not None:
            yield Frame(t=t + FRAME_DELAY_S, image=run.frame(i))
