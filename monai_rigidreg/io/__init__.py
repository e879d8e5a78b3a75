"""Reading and writing: volumes, DICOM series, the early reads of the ``register`` command, output folders.

- :mod:`~monai_rigidreg.io.volumes`: :func:`load_volume` (NIfTI, MHA, NRRD, DICOM folders), :func:`save_volume`,
  :func:`resample`, the output-folder checks, ``MetaTensor`` conversion.
- :mod:`~monai_rigidreg.io.dicom_series`: which series a folder holds, which one is read, reading it at the true slice
  positions.
- :mod:`~monai_rigidreg.io.prefetch`: both inputs read in worker threads while torch is imported; the NIfTI
  completeness and NaN checks.
- :mod:`~monai_rigidreg.io.staging`: an output folder written aside and renamed into place when complete.
- :mod:`~monai_rigidreg.io.shared_data`: the folder of the real CTs the tests and benchmarks use.

The names below are exported here on first use (``from monai_rigidreg.io import load_volume``), so importing
:mod:`monai_rigidreg.io.prefetch` does not import torch.
"""

from monai_rigidreg.core.lazy_exports import lazy_exports

_VOLUMES = "monai_rigidreg.io.volumes"
_TRANSFORMS = "monai_rigidreg.export.transform_files"
_SERIES = "monai_rigidreg.io.dicom_series"
_NAMES = {
    "VOLUME_SUFFIXES": _VOLUMES, "TRANSFORM_SUFFIXES": _TRANSFORMS, "load_volume": _VOLUMES, "save_volume": _VOLUMES,
    "check_volume": _VOLUMES, "list_dicom_series": _SERIES, "resample": _VOLUMES, "write_transform": _TRANSFORMS,
    "read_transform": _TRANSFORMS, "sitk_to_metatensor": _VOLUMES, "metatensor_to_sitk": _VOLUMES,
    "check_output_path": _VOLUMES, "check_output_dir": _VOLUMES, "make_dirs": _VOLUMES,
    "remove_made_dirs": _VOLUMES, "check_distinct_inputs": _SERIES, "describe_dicom_series": _SERIES,
    "select_dicom_series": _SERIES, "grids_overlap": _VOLUMES, "as_image": _VOLUMES,
}
__all__ = list(_NAMES)
# also the old module's other public names
__getattr__, __dir__ = lazy_exports(__name__, {**_NAMES, "grid_within": _VOLUMES, "RIGID_TRANSFORM_TYPES": _TRANSFORMS,
                                               "read_dicom_series": _SERIES})
