"""eventrecon: dynamic 3D scene reconstruction from multi-view event cameras.

The library is organised by role (see ``docs/architecture.md``):

- :mod:`eventrecon.events`     event arrays, decayed prefix accumulation, Bayer mask
- :mod:`eventrecon.sim`        procedural scenes, sensor effects, simulation
- :mod:`eventrecon.data`       dataset layout (read/write), segments, ray batching
- :mod:`eventrecon.render`     cameras, rays, clipping, samplers, the renderer protocol
- :mod:`eventrecon.fields`     the Field interface and the NeRF MLP
- :mod:`eventrecon.kernels`    compiled CPU kernels and the switch that chooses them
- :mod:`eventrecon.engine`     LightningModule, losses, runner, callbacks, checkpoints
- :mod:`eventrecon.evaluation` held-out rendering and scoring, PSNR/SSIM/LPIPS
- :mod:`eventrecon.results`    run records and machine facts
- :mod:`eventrecon.report`     tables and accuracy-vs-time
- :mod:`eventrecon.config`     Hydra resolvers, dataset names, override checks
- :mod:`eventrecon.capture`    USB discovery and CRF calibration
- :mod:`eventrecon.common`     errors, colour transfer, atomic files, locks, progress

Command-line entry points: ``python -m eventrecon.simulate``, ``.convert``,
``.evaluate``, ``.rig``, ``.report``.
"""

__version__ = "0.1.0"

#: Time span of a sequence in the published layout: events and frames carry t in [0, 1000].
TIME_SPAN: float = 1000.0

from eventrecon.config.resolvers import register_resolvers as _register_resolvers  # noqa: E402

_register_resolvers()  # ${paper_steps:...} in conf/ resolves wherever eventrecon is imported
