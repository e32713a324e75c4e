"""What runs a session: live sessions, their worker threads and where each session's mapper lives.

* :mod:`server.runtime.sessions` — :class:`LiveSession` and :class:`SessionManager`: ordering, durability
  before the ack, backpressure, restore, leases
* :mod:`server.runtime.worker` — one thread per session feeding its mapper in order; events, snapshots, replay
* :mod:`server.runtime.mapper_host` — where a mapper runs: in process (behind a gate);
  :mod:`server.runtime.process_host` in child processes, :mod:`server.runtime.ray_backend` in Ray actors
* :mod:`server.runtime.model` — the service's only window on :class:`hippomap.mapper.Mapper`
* :mod:`server.runtime.loop_calls` — calls from other threads onto the event loop, one wake-up per burst
"""
