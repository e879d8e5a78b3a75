"""The files made from a registration result.

- :mod:`~monai_rigidreg.export.outputs`: :func:`~monai_rigidreg.export.outputs.write_outputs`, the output folder
  of a registration (written aside, moved into place when complete).
- :mod:`~monai_rigidreg.export.transform_files`: the ITK transform file (``transform.tfm`` / ``.h5``), read and
  written.
- :mod:`~monai_rigidreg.export.qc_figure`: the QC figure (``qc.png``).
- :mod:`~monai_rigidreg.export.dicom_reg`: the DICOM Spatial Registration object (``registration.dcm``).
- :mod:`~monai_rigidreg.export.elastix_params`: the elastix parameter file (``TransformParameters.txt``).
- :mod:`~monai_rigidreg.export.couch_shifts`: the correction as IEC 61217 couch shifts (``result.json``).
- :mod:`~monai_rigidreg.export.provenance`: the audit trail (``result.json``).
"""

from monai_rigidreg.core.lazy_exports import lazy_exports

__all__ = ["couch_shifts", "dicom_reg", "elastix_params", "outputs", "provenance", "qc_figure", "transform_files"]

__getattr__, __dir__ = lazy_exports(__name__, {})  # submodules imported on first attribute access
