"""hippomap's web service: the mapper served to robots over HTTP and websockets.

The server is deliberately thin: it validates inputs, stores them durably, schedules
them to one :class:`hippomap.mapper.Mapper` per session and serialises the answers.
All model logic stays in :mod:`hippomap`. Test scaffolding (a live server in a subprocess,
synthetic robot data) is in the repository's ``tests/support``, not in this package.

Sub-packages, one concept each (each one's ``__init__`` lists its modules):

* :mod:`server.api`      — the FastAPI routes, one module per resource, and their shared dependencies
* :mod:`server.formats`  — what goes over the wire: inputs parsed and validated (4xx naming the problem),
  image headers, the websocket messages, request/response bodies, query answers serialised
* :mod:`server.security` — tokens, roles and who sees which session; request rates; what a session may cost
* :mod:`server.runtime`  — live sessions (ordering, durability, backpressure, restore), their worker
  threads, and where each mapper runs (in process, child processes, Ray actors)
* :mod:`server.storage`  — the storage interface, its shared SQL, SQLite (embedded) and PostgreSQL (replicas)

Top-level modules:

* :mod:`server.app`      — ``create_app``: the app, its lifespan, the routers and the viewer mounted
* :mod:`server.viewer`   — the one wiring to the viewer (package ``web``): live sessions as its sources
* :mod:`server.settings` — limits, paths and intervals (one pydantic model)
* :mod:`server.metrics`  — Prometheus metrics; :mod:`server.logs` structured (JSON) logs
* :mod:`server.cli`      — ``hippomap serve``; :mod:`server.demo` its simulated robot (``--demo``)
"""
