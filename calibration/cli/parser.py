"""The parser of ``python -m calibration``: every command's flags and their help, one function a
command; the choices come from the modules that own them."""

from __future__ import annotations

import argparse

from jaxmpm.cli import add_scene_arguments, add_threads_argument, side_walls_argument
from jaxmpm.precision import DTYPES
from jaxmpm.scenes import SCENE_NAMES
from jaxmpm.scenes.collapse import S4_SIDE

from ..batch.sweep import MODES as SWEEP_MODES
from ..data.parse import TIME_UNITS, UNITS
from ..inference.surrogates import EMULATORS
from ..optim.lm import DEFAULT_JACOBIAN, DEFAULT_MODEL
from ..optim.lm import JACOBIANS as LM_JACOBIANS
from ..optim.options import LM_MODELS, METHODS
from ..problem.options import JACOBIANS, WEIGHTINGS
from .args import design_scene

__all__ = ["build_parser"]


def _common(p, data: bool = True) -> None:
    if data:
        p.add_argument("experiments", nargs="*", metavar="EXPERIMENT.toml",
                       help="experiment files (docs/experiments.md): the set-up, its measurements and what to fit; "
                            "several: one material fitted to all of them")
        p.add_argument("--scene", default=None, choices=SCENE_NAMES,
                       help="a named scene the data come from (instead of an experiment file)")
        p.add_argument("--data", action="append", default=[], metavar="FILE.csv",
                       help="a deposit profile (project CSV or WebPlotDigitizer export); repeat for several times")
        p.add_argument("--front", default=None, metavar="FILE.csv", help="a front history (t_s,xf_m)")
        p.add_argument("--front-correlation-time", type=float, default=None, metavar="SECONDS",
                       help="the front's errors are exponentially correlated over this time (FrontTarget."
                            "correlation_time; default: independent). A fit with --front reports the estimate "
                            "from its residuals (front_residual_correlation): refit with it")
        p.add_argument("--units", default=None, choices=tuple(UNITS),
                       help="length units of files that do not state them (WebPlotDigitizer exports)")
        p.add_argument("--time-units", default=None, choices=tuple(TIME_UNITS), help="time units of a front file")
        p.add_argument("--dataset", default=None, metavar="NAME",
                       help="the dataset to take from multi-dataset WebPlotDigitizer exports (default: the first)")
        p.add_argument("--sort", action="store_true",
                       help="sort points given in WebPlotDigitizer click order by x (or t); duplicates are refused")
        p.add_argument("--clip-noise", action="store_true",
                       help="set heights in [-1e-3 max h, 0) to zero (digitisation noise); lower ones are refused")
        p.add_argument("--weight-profile", type=float, default=None,
                       help="weight of the profile misfit (default: the experiment file's, else 1)")
        p.add_argument("--weight-front", type=float, default=None,
                       help="weight of the front misfit (default: the experiment file's, else 1)")
        p.add_argument("--weighting", choices=WEIGHTINGS, default="block",
                       help="block: each profile and the front history weigh their weight in total, whatever their "
                            "length (the default); row: every point weighs it (the noise-weighted fit, most "
                            "efficient when all points have the same relative noise)")
        p.add_argument("--front-threshold", type=float, default=None,
                       help="height (m) below which the deposit has ended, for the front (default dx/ppc/2)")
    add_scene_arguments(p, scene_choices=False)
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--json", action="store_true", help="print one JSON object")


def _fit_options(p, default_keys: str | None) -> None:
    p.add_argument("--fit", default=default_keys, metavar="KEYS",
                   help="comma-separated parameters to fit, from beta,mu1,mu2,I0,xi (default: the experiment "
                        "file's [fit] keys)")
    p.add_argument("--method", choices=METHODS, default="lm")
    p.add_argument("--steps", type=int, default=None,
                   help="maximum iterations (default 25 for lm, 50 for lm with --lm-jacobian broyden, 150 for adam)")
    p.add_argument("--lm-model", choices=LM_MODELS, default=DEFAULT_MODEL,
                   help="LM's model of the loss's curvature: J^T J plus a secant estimate of the residuals' own "
                        "curvature wherever that forecast the last step better (adaptive, the default: Gauss-Newton's "
                        "steps where the residuals vanish, half the iterations where the model cannot reach the "
                        "data), or J^T J alone (gauss-newton, before 2026-12; docs/fitting.md)")
    p.add_argument("--lm-jacobian", choices=LM_JACOBIANS, default=DEFAULT_JACOBIAN,
                   help="where LM takes a trial's Jacobian from: its own forward-mode runs (exact) or one run of its "
                        "residuals and Broyden's update of the last Jacobian (broyden: the exact one again wherever a "
                        "step from the estimate fails or would stop; docs/fitting.md)")
    p.add_argument("--out", default=None, metavar="FILE.h5",
                   help="the fit's file: its history (written after every iteration), its setup and its end point, "
                        "what posterior reads (a search's: its best start's)")
    p.add_argument("--resume", action="store_true",
                   help="continue the fit stored in --out (it must be a history of the same problem)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --out with a new fit")
    p.add_argument("--plot", default=None, metavar="DIR", help="write the figures into DIR")
    p.add_argument("--reference-noise", type=float, default=0.01,
                   help="noise (fraction of the data scale) at which identifiability is judged (default 0.01)")
    p.add_argument("--threshold", type=float, default=0.1,
                   help="a parameter is constrained if its 95%% half-width is below this fraction (default 0.1)")
    p.add_argument("--workers", type=int, default=None, metavar="N",
                   help="single-threaded worker processes for the independent runs (the Jacobian's columns, the "
                        "starts, the extra runs of the verdict); default: the number of cores, or $JAXMPM_WORKERS; "
                        "1: everything in this process")
    p.add_argument("--roundoff-samples", type=int, default=8, metavar="N",
                   help="perturbed runs at the end point that measure the run's own round-off scatter, for the "
                        "verdict and the interval (default 8, one forward run each; 0: not measured)")
    p.add_argument("--restarts", type=int, default=2, metavar="N",
                   help="where the probe finds a lower loss near the end point, fit again from the lowest point it "
                        "ran, at most N times (default 2; restarts in the JSON)")
    p.add_argument("--probe", action=argparse.BooleanOptionalAction, default=True,
                   help="run the model about a fit's end point, at 1, 2, 4 and 8 times its 95%% half-width along "
                        "each principal direction (8 runs a key), and call it no fit where the loss is lower there "
                        "(a rough loss, or a stop on a slope; probe in the JSON; default on)")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m calibration", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    for add in (_add_fit, _add_posterior, _add_sweep, _add_bench, _add_law, _add_flow_rule, _add_coverage, _add_design,
                _add_twin):
        add(sub)
    for command in sub.choices.values():
        add_threads_argument(command)
    return parser


def _add_fit(sub) -> None:
    fit = sub.add_parser("fit", help="fit parameters to a measured deposit profile and/or front history")
    _common(fit)
    _fit_options(fit, None)
    fit.add_argument("--init", action="append", default=[], metavar="KEY=VALUE", help="starting value")
    fit.add_argument("--lr", type=float, default=0.05, help="Adam learning rate (in the unconstrained variables)")
    fit.add_argument("--shared", default=None, metavar="KEYS",
                     help="with several experiment files: the fitted keys that are one value for all of them; every "
                          "other fitted key is fitted per file, reported as KEY@FILE (default: all keys shared)")
    fit.add_argument("--jacobian", choices=JACOBIANS, default="ad",
                     help="LM Jacobian: forward-mode autodiff, or central differences for long violent runs")
    fit.add_argument("--noise", type=float, default=None,
                     help="known noise of the data (fraction of the peak height); default: estimated")
    fit.add_argument("--starts", type=int, default=None, metavar="K",
                     help="global search: Levenberg-Marquardt from K space-filling starts in one batch (default 8 "
                          "without --init, --resume, --method adam or --jacobian fd; else 1)")
    fit.add_argument("--search-seed", type=int, default=0, help="seed of the starts' Sobol design (default 0)")
    fit.add_argument("--coarse", type=float, default=None, metavar="F",
                     help="coarse-to-fine search: the starts run first at F times the grid spacing, then the best "
                          "--refine minima are refined at the requested one (F > 1; needs a search)")
    fit.add_argument("--refine", type=int, default=2, metavar="N",
                     help="coarse minima refined at the requested resolution (default 2; all within the noise of "
                          "the best if more)")
    fit.add_argument("--sampling-seeds", type=int, default=0, metavar="K",
                     help="K other draws of the particles at the end point: the sampling's share of the interval "
                          "(stderr_sampling; one forward run each; default 0: not measured)")
    fit.add_argument("--grid-check", type=float, default=1.5, metavar="RHO",
                     help="the grid's share of the interval: the fit's objective rebuilt at RHO times the grid "
                          "spacing, two particle draws there at the end point (stderr_grid, grid; about two thirds "
                          "of one forward run in 2D; default 1.5; 0: not measured)")
    _grid_levels(fit)
    fit.add_argument("--grid-ladder", type=int, default=None, metavar="N",
                     help="fit on N grids (2 or 3: dx x RHO^(N-1) ... dx, RHO from --grid-check), the coarsest from "
                          "the starts and each finer from the coarser one's point; the grid term from the fitted "
                          "points, and with 3 grids that converge the point extrapolated to dx -> 0 (ladder in the "
                          "JSON; docs/grid_term.md)")


def _grid_levels(p) -> None:
    p.add_argument("--grid-levels", type=int, default=1, metavar="N",
                   help="coarser grids for the grid term: 1 (RHO x dx; default) or 2 (also RHO^2 x dx): the order "
                        "the three grids show, or a wider term where they oscillate")


def _add_posterior(sub) -> None:
    post = sub.add_parser("posterior", help="the checks beyond Gauss-Newton around a fit's point: profile "
                                            "likelihoods, grid, NUTS and emulated posteriors")
    post.add_argument("fit_file", metavar="FIT.h5", help="a fit's file (python -m calibration fit --out FIT.h5): "
                      "its objective is built again from the files it names")
    post.add_argument("--profiles", type=int, default=0, metavar="N",
                      help="profile likelihood of every fitted key at N values over +-4 standard errors, the others "
                           "refitted at each (calibration.inference.likelihood; default 0: off)")
    post.add_argument("--posterior", type=int, default=0, metavar="N",
                      help="the posterior of one or two keys (flat prior) by quadrature on an N-point grid per key "
                           "over +-4 standard errors (N^k runs; default 0: off)")
    post.add_argument("--nuts", type=int, default=0, metavar="N",
                      help="the posterior of every fitted key by NUTS (calibration.inference.mcmc, needs [bayes]): N "
                           "draws per chain after N/2 (at least 20) warm-up steps, with R-hat and ESS (default 0: off)")
    post.add_argument("--emulated", type=int, default=0, metavar="N",
                      help="the posterior of every fitted key from NUTS on an emulator of the residuals, corrected by "
                           "the model's runs at N >= 30 draws (calibration.inference.emulator; also where the "
                           "verdict refuses an interval, with --noise or the estimated noise; default 0: off)")
    post.add_argument("--emulator", choices=tuple(EMULATORS), default="corrected",
                      help="--emulated's emulator: a quadratic per residual corrected by a Gaussian process through "
                           "the design points' values and slopes (default), or the quadratic alone")
    post.add_argument("--chains", type=int, default=4, metavar="C", help="chains, one after the other (default 4)")
    post.add_argument("--model-error", type=int, default=4, metavar="K",
                      help="the model's own error in every check's likelihood: K other particle draws and the grid "
                           "term's coarse runs at the fit's point, added to the data's noise by block (K + 3 runs; "
                           "default 4; 0: the data's noise alone)")
    post.add_argument("--prior", action="append", default=[], metavar="KEY=MEAN:SD",
                      help="a key measured by another experiment (an incline's I0): a normal prior in the posteriors "
                           "of --nuts and --emulated, beside the flat one in the bounds (repeat for several keys)")
    post.add_argument("--noise", type=float, default=None,
                      help="known noise of the data (fraction of the peak height); default: the fit's")
    post.add_argument("--grid-check", type=float, default=1.5, metavar="RHO",
                      help="the --nuts and --emulated posteriors' grid term: the same posterior at RHO x dx (about "
                           "RHO^-3 of its cost per level in 2D), the shift of its mean in ci95_with_grid; the model "
                           "error's coarse grid (default 1.5; 0: not measured)")
    _grid_levels(post)
    post.add_argument("--workers", type=int, default=None, metavar="N",
                      help="single-threaded worker processes for the model runs (default: the number of cores)")
    post.add_argument("--plot", default=None, metavar="DIR", help="the profile likelihoods and posterior into DIR")
    post.add_argument("--json", action="store_true", help="print one JSON object")


def _add_sweep(sub) -> None:
    sweep = sub.add_parser("sweep", help="the loss over a grid or a Latin hypercube of parameters")
    _common(sweep)
    sweep.add_argument("--over", action="append", default=[], metavar="KEY=LO:HI[:N]", help="swept parameter")
    sweep.add_argument("--lhs", type=int, default=None, metavar="N", help="N Latin-hypercube samples instead of a grid")
    sweep.add_argument("--lhs-seed", type=int, default=0, help="seed of the Latin hypercube (--seed seeds "
                       "the particle sampling)")
    sweep.add_argument("--chunk", type=int, default=None, help="members per vmapped chunk (default: by memory)")
    sweep.add_argument("--mode", choices=SWEEP_MODES, default="auto")
    sweep.add_argument("--cluster", default=None, metavar="local:N|tcp://HOST:PORT",
                       help="run the chunks as Dask tasks: on N local worker processes, or on the workers of a "
                            "running scheduler (the 'cluster' extra); --chunk is then the members per task")
    sweep.add_argument("--retries", type=int, default=2,
                       help="with --cluster: extra attempts of a task whose worker died or that raised (default 2)")
    sweep.add_argument("--out", default=None, metavar="FILE.h5", help="every member's loss, status and residuals")
    sweep.add_argument("--overwrite", action="store_true", help="replace an existing --out")
    sweep.add_argument("--plot", default=None, metavar="DIR",
                       help="the loss over the swept key, or the landscape over two (a grid, not --lhs)")


def _add_bench(sub) -> None:
    be = sub.add_parser("bench", help="time a forward run, the forward-mode Jacobian and the reverse-mode gradient")
    be.add_argument("--fit", default="beta,mu1,mu2,I0,xi", metavar="KEYS", help="parameters (default all five)")
    be.add_argument("--dx", type=float, default=S4_SIDE / 16, help="grid spacing of the S4 scene, m")
    be.add_argument("--quick", action="store_true", help="dx = L/8 and 0.2 s")
    be.add_argument("--repeat", type=int, default=2)
    be.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="a scene parameter (e.g. --set pc0=500 --set xi=50)")
    be.add_argument("--dtype", choices=DTYPES, default="float32")
    be.add_argument("--json", action="store_true", help="print one line of JSON")


def _add_flow_rule(sub) -> None:
    rule = sub.add_parser("flow-rule", help="fit mu1, mu2 and I0 (and the side walls' mu_w) to steady flows down "
                                             "an incline (a flow-rule table)")
    rule.add_argument("table", metavar="TABLE.csv|EXPERIMENT.toml",
                      help="a flow-rule table (slope_deg,h_m,u_m_s; docs/data_files.md) or an incline experiment "
                           "file ([experiment] kind = \"incline\": its material, table and [fit])")
    rule.add_argument("--fit", default=None, metavar="KEYS",
                      help="parameters to fit (default: the file's [fit] keys, else mu1,mu2,I0)")
    rule.add_argument("--init", action="append", default=[], metavar="KEY=VALUE",
                      help="start of a fitted key (default: the material's value)")
    rule.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                      help="a parameter held fixed: the grain diameter d, rho, rho_s, or a key not fitted")
    rule.add_argument("--side-walls", type=side_walls_argument, default=None, metavar="WIDTH,FRICTION[,K]",
                      help="the chute's side walls: its width (m), the walls' Coulomb friction (a number, or mu_w: "
                           "the parameter, set with --set mu_w=... and fitted with --fit ...,mu_w) and the lateral "
                           "pressure ratio K (default 1), e.g. 0.05,0.3 (default: the incline file's, else none)")
    rule.add_argument("--steps", type=int, default=100)
    rule.add_argument("--plot", default=None, metavar="DIR", help="draw flow_rule.png in DIR (made if missing)")
    rule.add_argument("--json", action="store_true")


def _add_law(sub) -> None:
    law = sub.add_parser("law", help="fit the S5 runout-against-aspect-ratio law and predict unused aspect ratios")
    law.add_argument("--fit", default="mu1,mu2", metavar="KEYS", help="parameters to fit (default mu1,mu2)")
    law.add_argument("--train", default="0.5,1,4", help="aspect ratios used in the fit")
    law.add_argument("--test", default="2,8", help="aspect ratios only predicted")
    law.add_argument("--sand", action="store_true", help="the sand law of Lube et al. 2005 instead of glass beads")
    law.add_argument("--law", default=None, metavar="FILE.csv",
                     help="a scaling-law table (a,dL_over_L0), "
                          "e.g. experiments_data/scaling_laws/runout_glass_beads.csv")
    law.add_argument("--dx", type=float, default=None, help="grid spacing, m (default L0/10)")
    law.add_argument("--ppc", type=float, default=None, help="particles per cell and axis (default: the scenes')")
    law.add_argument("--side-walls", type=side_walls_argument, default=None, metavar="WIDTH,FRICTION[,K]",
                     help="every column in a channel of this width (m) whose walls have this Coulomb friction "
                          "(and lateral pressure ratio K, default 1), e.g. 0.1,0.3 (default: plane strain)")
    law.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="material parameter")
    law.add_argument("--steps", type=int, default=15)
    law.add_argument("--jacobian", choices=JACOBIANS, default="fd")
    law.add_argument("--fd-step", type=float, default=0.05, help="relative step of the central differences")
    law.add_argument("--out", default=None, metavar="FILE.h5")
    law.add_argument("--overwrite", action="store_true", help="replace an existing --out")
    law.add_argument("--plot", default=None, metavar="DIR")
    law.add_argument("--no-progress", action="store_true")
    law.add_argument("--json", action="store_true")


def _add_coverage(sub) -> None:
    cov = sub.add_parser("coverage", help="twins over many noise seeds: how often the 95 %% intervals hold the truth")
    cov.add_argument("--fit", default="beta,mu1", metavar="KEYS", help="parameters to fit (default beta,mu1)")
    cov.add_argument("--seeds", type=int, default=20, help="noise seeds 0..N-1 (default 20)")
    cov.add_argument("--noise", type=float, default=0.02, help="Gaussian noise, fraction of the peak height")
    cov.add_argument("--quick", action="store_true", help="the twin's coarse grid (dx = L/8), about 25 s a seed")
    cov.add_argument("--dx", type=float, default=None, help="grid spacing, m (default: the twin's)")
    cov.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="a true scene parameter")
    cov.add_argument("--steps", type=int, default=None, help="LM iterations per fit (default 25)")
    cov.add_argument("--plot", default=None, metavar="DIR", help="every seed's interval against the truth")
    cov.add_argument("--no-progress", action="store_true")
    cov.add_argument("--json", action="store_true")


def _add_design(sub) -> None:
    de = sub.add_parser("design", help="which measurements constrain which keys: expected 95 %% half-widths of "
                                       "candidate observation sets before the experiment")
    de.add_argument("--scene", required=True, type=design_scene, metavar="SCENE|EXPERIMENT.toml",
                    help="the experiment's set-up: a collapse scene "
                         f"({', '.join(n for n in SCENE_NAMES if n != 'elastic-block')}) or an experiment file")
    _common(de, data=False)
    de.add_argument("--fit", required=True, metavar="KEYS", help="comma-separated keys to calibrate")
    de.add_argument("--at", action="append", default=[], metavar="KEY=VALUE",
                    help="the parameter point (default: the scene's values)")
    de.add_argument("--noise", type=float, default=0.02,
                    help="expected noise, a fraction of the profile's peak (and of the column's length for the "
                         "front, of the top's height for the top) (default 0.02)")
    de.add_argument("--noise-front", type=float, default=None, help="the front's noise, if not --noise")
    de.add_argument("--noise-top", type=float, default=None, help="the top height's noise, if not --noise")
    de.add_argument("--tolerance", type=float, default=0.1,
                    help="the 95 %% half-width every key should reach, a fraction of its value (default 0.1)")
    de.add_argument("--times", default=None, metavar="T1,T2,...",
                    help="profile times during the flow, s (default t_end x 0.1, 0.2, 0.4)")
    de.add_argument("--variant", action="append", default=[], metavar="LABEL:KEY=VALUE[,...]",
                    help="another experiment on the same material: the scene built with these builder arguments "
                         "changed (height, length, slope_deg, front_gate_speed, runout, t_end, ...); repeatable")
    de.add_argument("--incline", action="append", default=[], metavar="TABLE.csv|INCLINE.toml",
                    help="steady flows of the same material down an incline: a flow-rule table (its slopes, "
                         "thicknesses and quantity are the plan; its velocities are not used) or an incline "
                         "experiment file (its table and material); labelled by the file's stem; repeatable")
    de.add_argument("--noise-velocity", type=float, default=None,
                    help="an incline velocity's relative noise (default: the table's stated noise, else 0.02)")
    de.add_argument("--sampling-seeds", type=int, default=0, metavar="K",
                    help="K other particle draws per experiment: the sampling's share (default 0: not measured)")
    de.add_argument("--grid-check", type=float, default=1.5, metavar="RHO",
                    help="the grid's share, from each experiment rebuilt at RHO x dx (default 1.5; 0: not measured)")
    de.add_argument("--workers", type=int, default=None, metavar="N",
                    help="single-threaded worker processes for the extra runs (default: the number of cores)")
    de.add_argument("--plot", default=None, metavar="FIG.png", help="the expected 95 %% regions of the first two keys")


def _add_twin(sub) -> None:
    tw = sub.add_parser("twin", help="fit synthetic S4 data made with known parameters")
    _common(tw, data=False)
    _fit_options(tw, "beta,mu1,xi")
    tw.add_argument("--quick", action="store_true", help="a coarse grid (dx = L/8): about three minutes")
    tw.add_argument("--noise", type=float, default=0.0, help="Gaussian noise, fraction of the peak height")
    tw.add_argument("--noise-seed", type=int, default=0, help="seed of the noise")
    tw.add_argument("--landscape", type=int, default=None, metavar="N",
                    help="also sweep the loss on an N × N grid over the first two keys (figure with --plot)")
