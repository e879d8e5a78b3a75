"""Training and evaluation glue for MONAI engines: batch preparation, criterion, metrics, handlers, data."""

from monai_rigidreg.engine.batch import RegistrationPrepareBatch
from monai_rigidreg.engine.criterion import RegistrationCriterion, canonical_grid
from monai_rigidreg.engine.data import registration_transforms
from monai_rigidreg.engine.handlers import (
    LossTermsHandler,
    OptionalTensorBoardStatsHandler,
    ResumeHandler,
    TrainingCheckpointSaver,
    TrainingCurveHandler,
    TrainingProgressHandler,
    plot_history,
)
from monai_rigidreg.engine.inferer import StagedInferer
from monai_rigidreg.engine.metrics import RigidErrorHandler, RigidErrorMetric, error_handlers, from_registration_output
from monai_rigidreg.engine.sampler import MotionRange, RigidPairSampler, load_sources

__all__ = [
    "RegistrationPrepareBatch",
    "RegistrationCriterion",
    "StagedInferer",
    "RigidPairSampler",
    "MotionRange",
    "load_sources",
    "canonical_grid",
    "registration_transforms",
    "LossTermsHandler",
    "OptionalTensorBoardStatsHandler",
    "TrainingCurveHandler",
    "TrainingProgressHandler",
    "ResumeHandler",
    "TrainingCheckpointSaver",
    "plot_history",
    "RigidErrorHandler",
    "RigidErrorMetric",
    "error_handlers",
    "from_registration_output",
]
