"""hippomap's live browser viewer: a viser 3D scene and panel per mapping session.

The viewer is a thin layer over :class:`hippomap.mapper.Mapper`: every module draws one concept
(the map graph, the trajectories, the loop closures, the place field, the camera and its saccades,
...). Each session gets its own viser server bound to loopback, created on first view and closed
when idle; FastAPI serves viser's page and proxies its websocket (:mod:`web.routes`), so the
viewer shares the service's port and its authentication.

``hippomap/`` never imports this package; this package imports only ``hippomap``'s public objects.
"""
