"""hippomap's web service: the mapper served to robots over HTTP and websockets.

The server is deliberately thin: it validates inputs, stores them durably, schedules
them to one :class:`hippomap.mapper.Mapper` per session and serialises the answers.
All model logic stays in :mod:`hippomap`. Test scaffolding (a live server in a subprocess,
synthetic robot data) is in the repository's ``tests/support``, not in this package.

Modules, one concept each:

* :mod:`server.settings`  — limits, paths and intervals (one pydantic model)
* :mod:`server.store`     — the storage interface; :mod:`server.sqlite_store` its embedded backend,
  :mod:`server.postgres_store` the shared one (replicas; session leases)
* :mod:`server.auth`      — bearer tokens, roles and who sees which session
* :mod:`server.limits`    — request-rate buckets and the body-size guard
* :mod:`server.ingest`    — parsing and validating odometry and frames (4xx naming the problem)
* :mod:`server.images`    — image header sniffing (sizes before decoding) and encoding
* :mod:`server.protocol`  — the websocket stream's messages; the binary frame header it re-exports from
  :mod:`hippomap.protocol` (one definition, shared with the client)
* :mod:`server.model`     — the only module that touches the mapper (create, load, query)
* :mod:`server.worker`    — one thread per session feeding its mapper in order, snapshotting
* :mod:`server.mapper_host` — where a session's mapper runs: in process (behind a gate), in child processes
  (:mod:`server.process_host`), or a Ray actor (:mod:`server.ray_backend`)
* :mod:`server.loop_calls` — calls from other threads onto the event loop, one wake-up per burst
* :mod:`server.metrics`   — Prometheus metrics; :mod:`server.logs` structured (JSON) logs
* :mod:`server.sessions`  — live sessions: ordering, durability, backpressure, restore
* :mod:`server.views`     — serialisers: GraphML, g2o, TUM, place fields, saccade images
* :mod:`server.schemas`   — request/response bodies (the OpenAPI document)
* :mod:`server.api`       — the FastAPI routes; :mod:`server.app` assembles the app (and mounts the
  viewer of package ``web`` at ``/viewer/``)
* :mod:`server.cli`       — ``hippomap serve``; :mod:`server.demo` its simulated robot (``--demo``)
"""
