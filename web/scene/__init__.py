"""The 3D scene of a session viewer: one module a layer, built from a :class:`web.snapshot.MapSnapshot`.

Layers: the map graph (:mod:`~web.scene.map`), the trajectories (:mod:`~web.scene.trajectories`), loop
closures (:mod:`~web.scene.loops`), ground truth (:mod:`~web.scene.ground_truth`), the place field
(:mod:`~web.scene.place_field`), the robot (:mod:`~web.scene.pose`) and the time slider's replay
(:mod:`~web.scene.replay`). Shared by them: append-only layers sent in chunks (:mod:`~web.scene.chunks`),
a run's placement on a saved map (:mod:`~web.scene.placement`), the fitted camera
(:mod:`~web.scene.camera_fit`).
"""
