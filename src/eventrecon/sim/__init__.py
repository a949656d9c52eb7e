"""Procedural scenes, their exact renderer, sensor effects and event + frame simulation.

Modules, in data-flow order:

- :mod:`~eventrecon.sim.config`   field reading/validation, derived seeds, config hash
- :mod:`~eventrecon.sim.motion`, :mod:`~eventrecon.sim.texture`, :mod:`~eventrecon.sim.scene`
  objects (spheres, boxes, ground plane, deforming skirts, groups with joints) with
  motions and object-local textures
- :mod:`~eventrecon.sim.primitives`, :mod:`~eventrecon.sim.skirt` exact ray intersections
  (a deforming sheet: one quadratic per band)
- :mod:`~eventrecon.sim.tracer`, :mod:`~eventrecon.sim.raytrace` batched ray casting through
  the object hierarchy, Lambertian shading, per-ray time, subject masks
- :mod:`~eventrecon.sim.spec`     the scene-level settings, rig cameras, frame times
- :mod:`~eventrecon.sim.ideal`, :mod:`~eventrecon.sim.paths`, :mod:`~eventrecon.sim.merge`,
  :mod:`~eventrecon.sim.core_settings` the event core (adaptive sampling with a curvature
  bound and refined turns, interpolated crossings, time ordering without a global sort)
- :mod:`~eventrecon.sim.registry`, :mod:`~eventrecon.sim.event_effects`,
  :mod:`~eventrecon.sim.frame_effects` sensor effects by name, in the scene's order
- :mod:`~eventrecon.sim.event_sim`, :mod:`~eventrecon.sim.frames` events / frames of a rig
- :mod:`~eventrecon.sim.pipeline` ``simulate_dataset``, ``ensure_dataset`` (hash-keyed cache)

>>> from eventrecon.sim.pipeline import ensure_dataset      # doctest: +SKIP
>>> ensure_dataset({"name": "spheres", ...}, "data")         # doctest: +SKIP
PosixPath('data/spheres-1a2b3c4d5e')
"""
