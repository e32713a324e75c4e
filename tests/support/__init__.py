"""Scaffolding for the tests and benchmarks; not part of the product (the wheel does not ship it).

* :mod:`tests.support.live`             — a real server in a subprocess (:class:`~tests.support.live.LiveServer`),
  streaming inputs to it, a free port
* :mod:`tests.support.variants`         — the service variants (backend x store) the service suite runs against
* :mod:`tests.support.postgres_cluster` — a throwaway PostgreSQL cluster, a database per test server
* :mod:`tests.support.ray_head`         — a private Ray head the Ray-backed test servers join
* :mod:`tests.support.synthetic`        — synthetic robot data: a robot circling in front of a textured panorama
* :mod:`tests.support.reference`        — what a session must report (the mapper in-process) vs what it reports
* :mod:`tests.support.simfeed`          — a simulator run as mapper inputs, for the viewer's tests
* :mod:`tests.support.screenshot`       — a screenshot of a viewer page in headless Chromium (for the docs)

Benchmarks (``bench/``) run from the repository root import these too.
"""
