"""calibration: fit the μ(I) rheology's β, μ1, μ2, I0 and ξ to collapse data with jaxmpm.

The data flow: ``data`` (profiles and front histories, validated) -> ``objective`` (a scene's
residuals against them, an ``ObjectiveLike`` of ``protocol``, what every consumer calls;
``observe`` holds what the run observes, apart from the data, and compiles the pure functions
once per way of observing) -> ``fit`` (Levenberg–Marquardt or optax Adam, with bounds and a
resumable history; its options are ``options.FitOptions`` and ``options.JudgeOptions``, its JSON
``report.fit_report``) -> ``uncertainty`` (Gauss–Newton covariance, identifiability, and the verdict
whether a point is a fit of the data at all); ``search`` runs LM from many space-filling starts in
one vmapped batch and reports every minimum within the noise of the best. Both run the
``(init, update)`` optimisers of ``lm`` (Levenberg–Marquardt) and ``adam`` through the one loop of
``loop``, recording in ``history`` (saving and resuming); ``sweep`` evaluates the loss over many
parameter sets at once. The studies return dataclasses whose ``to_json()`` the command line
prints: ``twin`` fits data with known parameters (``TwinResult``), ``scaling`` fits the S5 runout
law (``LawResult``), ``bench`` times an evaluation (``BenchResult``), ``coverage`` runs twins over
noise seeds (``CoverageResult``). ``likelihood`` goes beyond Gauss–Newton: profile likelihoods, the
posterior of one or two keys on a grid, and predictions of held-out data with a band.
"""

from .bounds import DEFAULT_BOUNDS, FIT_KEYS, Bounds
from .data import (
    FrontHistory,
    Profile,
    RunoutLaw,
    list_datasets,
    load_front_history,
    load_measurements,
    load_profile,
    load_scaling_law,
)
from .fit import FitResult, fit
from .history import read_history
from .likelihood import GridPosterior, HeldOut, ProfileLikelihood, grid_posterior, predict_heldout, profile_likelihood
from .objective import CompositeObjective, FrontTarget, Objective, ProfileTarget
from .observe import ModelFunctions, Observations, model_functions
from .options import FitOptions, JudgeOptions, OptionError
from .protocol import ObjectiveLike, ResidualModel
from .report import fit_report
from .search import Minimum, SearchResult, coarse_to_fine, design_starts, search
from .uncertainty import (
                          GridCheck,
                          Uncertainty,
                          Verdict,
                          assess_fit,
                          gauss_newton_uncertainty,
                          grid_shift,
                          structural_noise,
)

__all__ = [
    "DEFAULT_BOUNDS", "FIT_KEYS", "Bounds", "GridPosterior", "HeldOut", "ProfileLikelihood", "grid_posterior",
    "predict_heldout", "profile_likelihood", "CompositeObjective", "FitResult", "FrontHistory", "FrontTarget",
    "Minimum", "ModelFunctions", "Objective", "Observations", "Profile", "ProfileTarget", "RunoutLaw", "SearchResult",
    "GridCheck", "Uncertainty", "Verdict",
    "assess_fit", "design_starts", "fit", "gauss_newton_uncertainty", "list_datasets", "load_front_history",
    "load_measurements",
    "coarse_to_fine", "load_profile", "model_functions", "load_scaling_law", "read_history", "search",
    "grid_shift", "structural_noise", "FitOptions", "JudgeOptions", "OptionError", "fit_report",
    "ObjectiveLike", "ResidualModel",
]
