"""Networks of monai-rigidreg: the learned regression, the weight-free Gauss-Newton stage, their composition, the
rigid spatial transformer and cascades.

The names below are exported here on first use (``from monai_rigidreg.networks import TwoStageRigidNet``, a bundle
config's ``monai_rigidreg.networks.TwoStageRigidNet``), so that ``monai-rigidreg register`` imports the networks it
runs only, not the reference design (``rigid_net``) or the spatial
transformer of training.
"""

from monai_rigidreg.core.lazy_exports import lazy_exports

_NAMES = {
    "ContextCorrelationNet": "monai_rigidreg.networks.context_net",
    "CorrelationRigidNet": "monai_rigidreg.networks.correlation_net",
    "local_cost_volume": "monai_rigidreg.networks.correlation_net",
    "unit_channels": "monai_rigidreg.networks.correlation_net",
    "weighted_rigid_fit": "monai_rigidreg.networks.correlation_net",
    "DualEncoderRigidNet": "monai_rigidreg.networks.rigid_net",
    "FUSIONS": "monai_rigidreg.networks.rigid_net",
    "GaussNewtonStage": "monai_rigidreg.networks.gauss_newton",
    "TwoStageRigidNet": "monai_rigidreg.networks.two_stage",
    "STAGE_KEYS": "monai_rigidreg.networks.two_stage",
    "RigidTransformer": "monai_rigidreg.networks.transformer",
    "cascade_register": "monai_rigidreg.networks.cascade",
    "CascadeRegistration": "monai_rigidreg.networks.cascade",
}
__all__ = list(_NAMES)
__getattr__, __dir__ = lazy_exports(__name__, _NAMES)
