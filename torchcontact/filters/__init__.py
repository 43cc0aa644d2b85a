"""Bayesian filters: Gaussian beliefs, Kalman/extended Kalman filters on Euclidean spaces and
pose manifolds, the Rauch–Tung–Striebel smoother, resampling, linear switching models, and the
Rao-Blackwellized particle filter that tracks discrete contact modes with a Kalman filter per
particle (with :func:`project_out_of_contact`, its constrained update out of the bodies), and
the baseline :class:`SimulatorParticleFilter` that steps its particles through the simulator;
:func:`fit_parameters` finds the physical parameters that maximize a filter's evidence.

Everything is functional (``predict(belief, ...) -> belief``), batched over leading dims and
differentiable; float32 and float64 both work.
"""

from torchcontact.filters._contact_model import (
    KinematicControl,
    PlanarContactModel,
    collect_modes,
    empirical_transition,
)
from torchcontact.filters._ekf import Dynamics, Measurement, ekf_predict, ekf_update
from torchcontact.filters._fit import FitResult, fit_parameters
from torchcontact.filters._gaussian import Gaussian
from torchcontact.filters._kalman import kf_predict, kf_update
from torchcontact.filters._manifold import (
    EUCLIDEAN,
    SE2,
    SE3,
    Euclidean,
    Manifold,
    SE2Pose,
    SE3Pose,
)
from torchcontact.filters._projection import project_out_of_contact
from torchcontact.filters._rbpf import RBPF, Proposal
from torchcontact.filters._rbpf_belief import RBPFBelief, SwitchingModel
from torchcontact.filters._resampling import (
    ResamplingMethod,
    effective_sample_size,
    optimal_resample,
    resample,
)
from torchcontact.filters._simulator_pf import (
    ParticleLogLikelihood,
    SimulatorParticleFilter,
    SimulatorPFBelief,
)
from torchcontact.filters._smoother import rts_smooth
from torchcontact.filters._spatial_contact_model import RobotControl, SpatialContactModel
from torchcontact.filters._switching import LinearSwitchingModel, ModeDynamics
from torchcontact.geometry import quat_exp, quat_log, wrap_angle

__all__ = [
    "EUCLIDEAN",
    "RBPF",
    "SE2",
    "SE3",
    "Dynamics",
    "Euclidean",
    "FitResult",
    "Gaussian",
    "KinematicControl",
    "LinearSwitchingModel",
    "Manifold",
    "Measurement",
    "ModeDynamics",
    "ParticleLogLikelihood",
    "PlanarContactModel",
    "Proposal",
    "RBPFBelief",
    "ResamplingMethod",
    "RobotControl",
    "SE2Pose",
    "SE3Pose",
    "SimulatorPFBelief",
    "SimulatorParticleFilter",
    "SpatialContactModel",
    "SwitchingModel",
    "collect_modes",
    "effective_sample_size",
    "ekf_predict",
    "ekf_update",
    "empirical_transition",
    "fit_parameters",
    "kf_predict",
    "kf_update",
    "optimal_resample",
    "project_out_of_contact",
    "quat_exp",
    "quat_log",
    "resample",
    "rts_smooth",
    "wrap_angle",
]
