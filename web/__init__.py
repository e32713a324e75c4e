"""hippomap's live browser viewer: a viser 3D scene and panel per mapping session.

The viewer is a thin layer over :class:`hippomap.mapper.Mapper`: every module draws one concept
(the map graph, the trajectories, the loop closures, the place field, the camera and its saccades,
...). Each session gets its own viser server bound to loopback, created on first view and closed
when idle; FastAPI serves viser's page and proxies its websocket (:mod:`web.routes`), so the
viewer shares the service's port and its authentication.

Layout: :mod:`web.scene` holds the 3D layers, :mod:`web.panels` the side panels; at the top are the
routes, the landing page, the per-session viewer and its hub, the mapper snapshot, settings and images.

``hippomap/`` never imports this package; this package imports only ``hippomap``'s public objects and
never the service (``server``): it reads a session through :class:`web.source.SessionSource`, and the
service's :mod:`server.viewer` adapts its live sessions to that protocol and mounts these routes.
"""
