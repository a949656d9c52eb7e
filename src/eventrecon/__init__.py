"""eventrecon: dynamic 3D scene reconstruction from multi-view event cameras.

The library is organised by role (see ``README.md``):

- :mod:`eventrecon.events`  event arrays, decayed prefix accumulation, Bayer mask
- :mod:`eventrecon.sim`     procedural scenes, renderer, sensor effects, simulation
- :mod:`eventrecon.data`    dataset layout (read/write), ray batching, DataModule
- :mod:`eventrecon.render`  cameras, rays, clipping, samplers, volume rendering
- :mod:`eventrecon.fields`  the Field interface and the NeRF MLP
- :mod:`eventrecon.losses`  the four losses and their schedules
- :mod:`eventrecon.module`  the LightningModule
- :mod:`eventrecon.metrics` PSNR / SSIM / LPIPS
- :mod:`eventrecon.report`  tables and accuracy-vs-time
- :mod:`eventrecon.capture` USB discovery and CRF calibration
"""

__version__ = "0.1.0"

#: Time span of a sequence in the published layout: events and frames carry t in [0, 1000].
TIME_SPAN: float = 1000.0

from eventrecon.config import register_resolvers as _register_resolvers  # noqa: E402

_register_resolvers()  # ${paper_steps:...} in conf/ resolves wherever eventrecon is imported
