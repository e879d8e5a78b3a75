"""The pieces every other subpackage builds on: no file I/O, no MONAI.

- :mod:`~monai_rigidreg.core.geometry`: the one owner of the conventions (parameters <-> 4x4 <-> ``Euler3DTransform``
  <-> torch ``theta``, LPS/RAS, TRE, angle wrap; ``docs/conventions.md``).
- :mod:`~monai_rigidreg.core.image_ops`: Gaussian smoothing, erosion, gradient magnitude, pyramid, local mean,
  masked NCC.
- :mod:`~monai_rigidreg.core.warp`: differentiable resampling of a volume by a 4x4 transform.
- :mod:`~monai_rigidreg.core.grid_sampling`: resampling onto a :class:`~monai_rigidreg.core.geometry.Grid`, HU
  normalization (the preprocessing of training and inference).
- :mod:`~monai_rigidreg.core.network_grid`: :class:`~monai_rigidreg.core.network_grid.NetworkGridSpec`, the network
  grid and where it is placed.
- :mod:`~monai_rigidreg.core.device`: device strings and CPU thread counts.
- :mod:`~monai_rigidreg.core.errors`: the package's exceptions and SIGTERM as an interrupt.
- :mod:`~monai_rigidreg.core.json_safe`: strict-JSON values (non-finite -> ``null``).
- :mod:`~monai_rigidreg.core.lazy_exports`: names a package exports from its modules on first use.
"""

from monai_rigidreg.core.lazy_exports import lazy_exports

__all__ = ["device", "errors", "geometry", "grid_sampling", "image_ops", "json_safe", "lazy_exports", "network_grid",
           "warp"]

__getattr__, __dir__ = lazy_exports(__name__, {})  # submodules imported on first attribute access
