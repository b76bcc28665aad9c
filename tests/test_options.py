"""The fit's option objects: every bad value refused once, by field, before anything runs; the
command line reports the same check under its flag."""

import dataclasses

import pytest

from calibration.cli.args import FLAGS, as_flag
from calibration.inference.options import JudgeOptions
from calibration.optim.options import FitOptions, split_fields
from calibration.optim.report import PosteriorOptions
from calibration.problem.options import DataOptions, FitRequest, OptionError, fit_request


@pytest.mark.parametrize("field, value, what", [
    ("method", "bfgs", "must be one of"),
    ("steps", 0, "a positive integer"),
    ("steps", 2.5, "a positive integer"),
    ("learning_rate", 0.0, "> 0"),
    ("learning_rate", float("nan"), "> 0"),
    ("clip", -1.0, "> 0"),
    ("grad_mode", "both", "one of"),
    ("stat_tol", -0.1, ">= 0"),
    ("max_rejections", 0, "an integer >= 1"),
    ("max_rejections", True, "an integer >= 1"),
    ("restarts", -1, "an integer >= 0"),
    ("restarts", 1.5, "an integer >= 0"),
])
def test_fit_options_refuse_bad_values(field, value, what):
    with pytest.raises(OptionError, match=what) as info:
        FitOptions(**{field: value})
    assert info.value.field == field and str(info.value).startswith(field)


@pytest.mark.parametrize("field, value, what", [
    ("noise", -0.01, ">= 0"),
    ("noise", {"profile": float("inf")}, ">= 0"),
    ("uncertainty", 1, "True or False"),
    ("probe", "yes", "True or False"),
    ("roundoff_samples", 1, "0 \\(not measured\\) or an integer >= 2"),
    ("sampling_seeds", 1, "0 \\(not measured\\) or an integer >= 2"),
    ("reference_noise", -1.0, ">= 0"),
    ("threshold", float("nan"), ">= 0"),
    ("grid_ratio", 1.0, "factor > 1"),
    ("grid_ratio", 0, "factor > 1"),
    ("grid_draws", 0, "an integer >= 1"),
    ("grid_levels", 3, "1 or 2"),
])
def test_judge_options_refuse_bad_values(field, value, what):
    with pytest.raises(OptionError, match=what):
        JudgeOptions(**{field: value})


@pytest.mark.parametrize("field, value, what", [
    ("weighting", "point", "one of"),
    ("jacobian", "cd", "one of"),
    ("front_threshold", 0.0, "a finite number > 0"),
    ("front_correlation_time", float("inf"), "a finite number > 0"),
    ("weight_profile", -1.0, "a finite number >= 0"),
    ("weight_front", float("nan"), "a finite number >= 0"),
])
def test_data_options_refuse_bad_values(field, value, what):
    with pytest.raises(OptionError, match=what) as info:
        DataOptions(**{field: value})
    assert str(as_flag(info.value)).startswith(FLAGS[field] + " must be")


def test_data_options_weights():
    assert DataOptions().weights() == {"profile": 1.0, "front": 1.0}
    assert DataOptions(weight_front=2.0).weights(None) == {"profile": None, "front": 2.0}
    assert DataOptions(weight_profile=0.0).weights() == {"profile": 0.0, "front": 1.0}


def test_options_are_frozen_and_defaults_valid():
    options, judge = FitOptions(), JudgeOptions()
    with pytest.raises(dataclasses.FrozenInstanceError):
        options.steps = 3
    assert judge.grid_ratio is None and judge.kwargs()["grid_draws"] >= 1


def test_differences_cover_every_field_but_steps_and_restarts():
    saved = FitOptions().to_json()
    assert FitOptions(steps=99).differences(saved) == []
    assert FitOptions(restarts=0).differences(saved) == []  # an outer loop: a resume may change it
    for field in dataclasses.fields(FitOptions):
        if field.name in ("steps", "restarts", "method", "grad_mode"):
            continue
        other = {"lm_model": "gauss-newton", "lm_jacobian": "broyden"}.get(field.name,
                                                                         getattr(FitOptions(), field.name) * 2)
        changed = dataclasses.replace(FitOptions(), **{field.name: other})
        assert [d.split(":")[0] for d in changed.differences(saved)] == [field.name]
    older = {k: v for k, v in saved.items() if k != "stat_tol"}  # a file written before stat_tol was recorded
    assert FitOptions().differences(older) == ["stat_tol: 0.1 now, not recorded in the file"]
    # A file from before Broyden's option was LM with exact Jacobians, which resumes as it was.
    before = {k: v for k, v in saved.items() if k != "lm_jacobian"}
    assert FitOptions().differences(before) == []
    assert [d.split(":")[0] for d in FitOptions(lm_jacobian="broyden").differences(before)] == ["lm_jacobian"]


def test_one_flag_table_for_every_field():
    names = {f.name for cls in (FitOptions, JudgeOptions, FitRequest, DataOptions, PosteriorOptions)
             for f in dataclasses.fields(cls)}
    assert set(FLAGS) == names
    assert str(as_flag(OptionError("grid_ratio", "must be > 1, got 0.5"))) == "--grid-check must be > 1, got 0.5"
    assert str(as_flag(OptionError("xtol", "must be >= 0"))) == "xtol must be >= 0"  # no flag: the field's name


def test_split_fields():
    run, judge = split_fields({"steps": 3, "grid_ratio": 1.5})
    assert run == {"steps": 3} and judge == {"grid_ratio": 1.5}
    with pytest.raises(TypeError, match="unexpected keyword arguments \\['stepz'\\]"):
        split_fields({"stepz": 3})


def test_fit_request_from_the_files_and_over_them():
    from calibration.data import FitSpec, with_measurements
    from jaxmpm.experiment import shipped_experiment

    s4 = shipped_experiment("cohesive-collapse")

    def E(fit):  # noqa: N802 - an experiment file whose [fit] is ``fit``
        return with_measurements(s4, fit=fit)

    a, b = E(FitSpec(keys=("beta", "mu1"), init={"beta": 0.2}, noise=0.01)), E(FitSpec(keys=("beta", "mu1")))
    assert fit_request([a]) == FitRequest(("beta", "mu1"), {"beta": 0.2}, 0.01)
    assert fit_request([a], keys=("mu1",), init={"mu1": 0.4}).keys == ("mu1",)
    assert fit_request([a], keys=("mu1",)) == FitRequest(("mu1",), {}, 0.01)  # the file's start of beta: not fitted
    with pytest.raises(OptionError, match="init differs between the experiment files"):
        fit_request([a, b])
    assert fit_request([a, b], init={"beta": 0.3}, noise=0.02) == FitRequest(("beta", "mu1"), {"beta": 0.3}, 0.02)
    with pytest.raises(OptionError, match="keys is required.*not every experiment file"):
        fit_request([a, E(None)])
    with pytest.raises(OptionError, match="gives starting values for \\['xi'\\]") as info:
        fit_request([], keys=("beta",), init={"xi": 40.0})
    assert str(as_flag(info.value)).startswith("--init gives starting values")
