"""The registration pipeline: a CBCT (moving) to a planning CT (fixed), one module per stage in call order.

- :mod:`~monai_rigidreg.registration.inputs`: the inputs checked once (paths, output folder, HU ranges, overlap).
- :mod:`~monai_rigidreg.registration.match_region`: the region to match (``roi=`` box or mask, ``match="bone"``).
- :mod:`~monai_rigidreg.registration.body`: the body mask and the couch left out of the match.
- :mod:`~monai_rigidreg.registration.search`: the global search for large offsets and the choice between starts.
- :mod:`~monai_rigidreg.registration.network_run`: the network grid's tensors and the network's runs from starts.
- :mod:`~monai_rigidreg.registration.last_level`: the last Gauss-Newton level at the inputs' resolution.
- :mod:`~monai_rigidreg.registration.classical`: SimpleITK / elastix (``refine=True`` and the baselines).
- :mod:`~monai_rigidreg.registration.confidence`: the failure signals, the swapped-input check and the score.
- :mod:`~monai_rigidreg.registration.region_check`: the ROI's structures matched block by block after the estimate.
- :mod:`~monai_rigidreg.registration.registrar`: :class:`RigidRegistrar`, the stages in call order;
  :mod:`~monai_rigidreg.registration.state`: what a call carries between them;
  :mod:`~monai_rigidreg.registration.result`: :class:`RegistrationResult`.
- :mod:`~monai_rigidreg.registration.api`: :func:`register`, the one-call function.
- :mod:`~monai_rigidreg.registration.files`: files in, files out (``register_files``);
  :mod:`~monai_rigidreg.registration.pairs`: many pairs in one process; and
  :mod:`~monai_rigidreg.registration.register_command`: ``monai-rigidreg register``.

The names below are exported here on first use, so importing the ``register`` command's module does not import
torch.
"""

from monai_rigidreg.core.lazy_exports import lazy_exports

_NAMES = {
    "RegistrationResult": "monai_rigidreg.registration.result",
    "RigidRegistrar": "monai_rigidreg.registration.registrar",
    "register": "monai_rigidreg.registration.api",
    "check_intensities": "monai_rigidreg.registration.inputs",
    "not_hu": "monai_rigidreg.registration.inputs",
    "fine_stage_switch": "monai_rigidreg.registration.registrar",
}
__all__ = list(_NAMES)
__getattr__, __dir__ = lazy_exports(__name__, {
    **_NAMES,
    # module constants the documentation names as ``monai_rigidreg.registration.X``
    "SEARCH_AGREE_MM": "monai_rigidreg.registration.search",
    "SAME_POSE_MM": "monai_rigidreg.registration.search",
    "EARLY_SWAP_MAX_CHANGE_MM": "monai_rigidreg.registration.registrar",
    "HU_AIR_LIMIT": "monai_rigidreg.registration.inputs",
    "EIGHT_BIT_RANGE": "monai_rigidreg.registration.inputs",
    "CONFIDENCE_THRESHOLD": "monai_rigidreg.registration.confidence",
})
