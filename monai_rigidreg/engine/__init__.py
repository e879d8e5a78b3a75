"""Training and evaluation glue for MONAI engines: batch preparation, criterion, metrics, handlers, data.

The names below are exported here on first use (PEP 562): importing the ``train`` command's module imports neither
torch nor MONAI (``monai-rigidreg --help`` builds its parser).
"""

from monai_rigidreg.core.lazy_exports import lazy_exports

_MODULES = {
    "batch": ("RegistrationPrepareBatch",),
    "criterion": ("RegistrationCriterion", "canonical_grid"),
    "data": ("registration_transforms",),
    "handlers": ("load_matching_weights", "LossTermsHandler", "OptionalTensorBoardStatsHandler", "ResumeHandler",
                 "TrainingCheckpointSaver", "TrainingCurveHandler", "TrainingProgressHandler", "plot_history"),
    "inferer": ("StagedInferer",),
    "metrics": ("RigidErrorHandler", "RigidErrorMetric", "error_handlers", "from_registration_output"),
    "sampler": ("MotionRange", "RigidPairSampler"),
    "sources": ("load_sources",),
    "threads": ("ThreadTuner",),
}
_NAMES = {name: f"monai_rigidreg.engine.{module}" for module, names in _MODULES.items() for name in names}
__all__ = list(_NAMES)
__getattr__, __dir__ = lazy_exports(__name__, _NAMES)
