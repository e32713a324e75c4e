"""What goes over the wire: inputs parsed and checked on the way in, answers serialised on the way out.

* :mod:`server.formats.ingest` — odometry and frames validated before anything is stored (4xx naming the problem)
* :mod:`server.formats.images` — image header sniffing (sizes before decoding) and encoding
* :mod:`server.formats.protocol` — the websocket stream's messages; the binary frame header it re-exports
  from :mod:`hippomap.protocol`
* :mod:`server.formats.schemas` — request and response bodies (the OpenAPI document)
* :mod:`server.formats.views` — query answers as GraphML, g2o, TUM, place fields, saccade images
"""
