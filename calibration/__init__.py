"""calibration: fit the μ(I) rheology's β, μ1, μ2, I0 and ξ to collapse data with jaxmpm.

One sub-package per role, read from the ground up (``data``, ``problem``, ``batch``, ``inference``,
``optim``, ``design``, ``studies``, ``plots``, ``cli``; docs/layout.md says what each holds). This face
re-exports what a user's script needs; everything else is reached by its module.
"""

from jaxmpm.datasets import list_datasets

from .data.collapse import read_measurements, with_measurements
from .data.loaders import FrontHistory, Profile, RunoutLaw, load_front_history, load_profile, load_scaling_law
from .data.measurements import load_measurements
from .inference.gauss_newton import Uncertainty, gauss_newton_uncertainty
from .inference.gridcheck import GridCheck, grid_shift
from .inference.gridpost import GridPosterior, HeldOut, grid_posterior, predict_heldout
from .inference.likelihood import ProfileLikelihood, profile_likelihood
from .inference.noise import structural_noise
from .inference.options import JudgeOptions
from .inference.verdict import Verdict, assess_fit
from .optim.fit import FitResult, fit
from .optim.history import read_history
from .optim.options import FitOptions
from .optim.report import fit_report
from .optim.search import Minimum, SearchResult, coarse_to_fine, design_starts, search
from .problem.bounds import DEFAULT_BOUNDS, FIT_KEYS, Bounds
from .problem.composite import CompositeObjective
from .problem.flow_rule import FlowRuleObjective
from .problem.objective import Objective
from .problem.observe import Observations
from .problem.options import OptionError
from .problem.protocol import ObjectiveLike, ResidualModel
from .problem.residuals import ModelFunctions, Problem, make_residuals, model_functions
from .problem.targets import FrontTarget, ProfileTarget

__all__ = [
    "DEFAULT_BOUNDS", "FIT_KEYS", "Bounds", "GridPosterior", "HeldOut", "ProfileLikelihood", "grid_posterior",
    "predict_heldout", "profile_likelihood", "CompositeObjective", "FitResult", "FrontHistory", "FrontTarget",
    "Minimum", "ModelFunctions", "Objective", "Observations", "Profile", "ProfileTarget", "RunoutLaw", "SearchResult",
    "GridCheck", "Uncertainty", "Verdict",
    "assess_fit", "design_starts", "fit", "gauss_newton_uncertainty", "list_datasets", "load_front_history",
    "load_measurements", "read_measurements", "with_measurements",
    "coarse_to_fine", "load_profile", "model_functions", "load_scaling_law", "read_history", "search",
    "grid_shift", "structural_noise", "FitOptions", "JudgeOptions", "OptionError", "fit_report",
    "ObjectiveLike", "ResidualModel", "Problem", "make_residuals", "FlowRuleObjective",
]
