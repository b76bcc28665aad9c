"""calibration.data: profile / front-history / scaling-law loaders and the shipped experiments_data."""

import json
import math
import pathlib

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import jaxmpm as jm
from calibration.data.flow_rule import load_flow_rule, load_h_stop
from calibration.data.incline import load_incline
from calibration.data.loaders import (
    FrontHistory,
    Profile,
    load_front_history,
    load_profile,
    load_scaling_law,
    read_table,
)
from calibration.data.measurements import load_setup
from jaxmpm import datasets as data
from jaxmpm.datasets import dataset_path, list_datasets

DATA = pathlib.Path(__file__).resolve().parent.parent / "experiments_data"


def write(tmp_path, text, name="p.csv", newline="\n"):
    path = tmp_path / name
    path.write_bytes(text.replace("\n", newline).encode())
    return path


def profile(**kw):
    base = {"x": [0.0, 0.01, 0.02, 0.05], "h": [0.04, 0.03, 0.01, 0.0], "experiment": "test", "time_s": 0.5,
            "source": "unit test", "synthetic": False, "meta": {}}
    return Profile(**{**base, **kw})


# --------------------------------------------------------------------------------------------
# Round trips
# --------------------------------------------------------------------------------------------


def test_profile_round_trip(tmp_path):
    meta = {"parameters": {"beta": 0.25, "xi": 50.0}, "status": 0, "note": "true", "digits": "12",
            "spaced": " padded ", "tags": [1, 2]}
    p = profile(meta=meta, synthetic=True)
    path = p.to_csv(tmp_path / "p.csv")
    q = load_profile(path)
    np.testing.assert_allclose(q.x, p.x, rtol=1e-6, atol=0)
    np.testing.assert_allclose(q.h, p.h, rtol=1e-6, atol=0)
    assert (q.experiment, q.time_s, q.source, q.synthetic, q.meta) == ("test", 0.5, "unit test", True, meta)
    assert q.path == str(path) and q.n == 4
    assert q.x.dtype == np.float64 and not q.x.flags.writeable
    r = load_profile(q.to_csv(tmp_path / "q.csv"))
    np.testing.assert_array_equal(r.x, q.x)  # exact at the printed precision
    np.testing.assert_array_equal(r.h, q.h)
    assert r.meta == q.meta and r.time_s == q.time_s


def test_profile_without_time_and_synthetic_flag(tmp_path):
    p = load_profile(profile(time_s=None, experiment="S4 (synthetic)").to_csv(tmp_path / "p.csv"))
    assert p.time_s is None and "time_s" not in (tmp_path / "p.csv").read_text()
    assert p.synthetic is False  # to_csv writes the field explicitly; an explicit key wins over the word
    path = write(tmp_path, "# experiment: S3 (synthetic, jaxmpm)\nx_m,h_m\n0,1\n1,1\n2,0\n", "s.csv")
    assert load_profile(path).synthetic  # no key: the word in experiment decides
    path = write(tmp_path, "# experiment: lab run\n# synthetic: true\nx_m,h_m\n0,1\n1,1\n2,0\n", "t.csv")
    assert load_profile(path).synthetic


@settings(max_examples=40, deadline=None)
@given(
    st.lists(st.tuples(st.floats(1e-3, 1.0), st.floats(0.0, 10.0)), min_size=3, max_size=30),
    st.floats(-1.0, 1.0),
)
def test_profile_round_trip_property(tmp_path_factory, rows, x0):
    x = x0 + np.cumsum([dx for dx, _ in rows])
    h = np.array([hh for _, hh in rows])
    h[0] = max(h[0], 1e-3)
    p = Profile(x=x, h=h, experiment="hyp", time_s=1.0)
    folder = tmp_path_factory.mktemp("rt")
    q = load_profile(p.to_csv(folder / "a.csv"))
    np.testing.assert_allclose(q.x, x, rtol=6e-7, atol=1e-300)
    np.testing.assert_allclose(q.h, h, rtol=6e-7, atol=1e-300)
    r = load_profile(q.to_csv(folder / "b.csv"))
    np.testing.assert_array_equal(r.x, q.x)
    np.testing.assert_array_equal(r.h, q.h)


def test_front_history_round_trip(tmp_path):
    f = FrontHistory(t=[0.0, 0.1, 0.2, 0.3], x_front=[0.2, 0.25, 0.3, 0.31], experiment="front (synthetic)",
                     source="test", meta={"front_definition": "max x"})
    g = load_front_history(f.to_csv(tmp_path / "f.csv"))
    np.testing.assert_allclose(g.t, f.t)
    np.testing.assert_allclose(g.x_front, f.x_front)
    assert g.synthetic is False and g.meta == f.meta and g.n == 4  # explicit synthetic: false in the header
    path = write(tmp_path, "# experiment: x\nt_s,xf_mm\n0,200\n0.1,250\n0.2,300\n", "mm.csv")
    np.testing.assert_allclose(load_front_history(path).x_front, [0.2, 0.25, 0.3])


def test_front_history_wpd_needs_both_units(tmp_path):
    path = write(tmp_path, "0,20\n100,25\n200,30\n", "wpd.csv")
    with pytest.raises(ValueError, match=r"wpd\.csv: the file has no units"):
        load_front_history(path, time_units="ms")
    with pytest.raises(ValueError, match=r"wpd\.csv: the file has no time units.*time_units='s'\|'ms'"):
        load_front_history(path, units="cm")
    f = load_front_history(path, units="cm", time_units="ms")
    np.testing.assert_allclose(f.t, [0.0, 0.1, 0.2])
    np.testing.assert_allclose(f.x_front, [0.2, 0.25, 0.3])


def test_front_history_time_must_increase(tmp_path):
    path = write(tmp_path, "t_s,xf_m\n0,0.2\n0.2,0.3\n0.1,0.25\n", "f.csv")
    with pytest.raises(ValueError, match=r"f\.csv: t is not strictly increasing: "
                                         r"line 3 \(t = 0\.2 s\) is followed by line 4"):
        load_front_history(path)
    assert load_front_history(path, sort=True).t.tolist() == [0.0, 0.1, 0.2]


# --------------------------------------------------------------------------------------------
# WebPlotDigitizer and delimiter variants
# --------------------------------------------------------------------------------------------

EXPECTED_X, EXPECTED_H = [0.01, 0.02, 0.04], [0.08, 0.07, 0.05]


@pytest.mark.parametrize("text, newline", [
    ("10,80\n20,70\n40,50\n", "\n"),                            # no header
    ("X,Y\n10,80\n20,70\n40,50\n", "\n"),                       # WPD X,Y header
    ("x,y\n10,80\n20,70\n40,50\n", "\r\n"),                     # lower case, Windows line endings
    ("10;80\n20;70\n40;50\n", "\n"),                            # semicolon
    ("10\t80\n20\t70\n40\t50\n", "\n"),                         # tab
    ("10,0;80,0\n20;70\n40,0;50\n", "\r\n"),                    # semicolon with decimal commas
    ("\ufeff10,80,\n20,70,\n40,50,\n", "\n"),                   # byte-order mark, trailing delimiter
    ("10 80\n20 70\n40 50\n", "\n"),                            # blanks
])
def test_wpd_variants(tmp_path, text, newline):
    p = load_profile(write(tmp_path, text, newline=newline), units="mm", experiment="digitised", time_s=0.5)
    np.testing.assert_allclose(p.x, EXPECTED_X)
    np.testing.assert_allclose(p.h, EXPECTED_H)
    assert p.experiment == "digitised" and p.time_s == 0.5 and not p.synthetic
    assert "WebPlotDigitizer" in p.source and "units mm" in p.source


def test_wpd_units(tmp_path):
    path = write(tmp_path, "1,8\n2,7\n4,5\n")
    np.testing.assert_allclose(load_profile(path, units="cm").x, EXPECTED_X)
    np.testing.assert_allclose(load_profile(path, units="m").x, [1.0, 2.0, 4.0])
    assert load_profile(path, units="m").experiment == "p"  # the file stem when nothing names it


def test_wpd_multi_dataset(tmp_path):
    text = ("Dataset 1,,Dataset 2,\nX,Y,X,Y\n10,80,1,2\n20,70,2,3\n40,50,3,4\n,,4,3\n")
    path = write(tmp_path, text, newline="\r\n")
    p = load_profile(path, units="mm")
    np.testing.assert_allclose(p.x, EXPECTED_X)
    assert p.meta["wpd_dataset"] == "Dataset 1" and "Dataset 1" in p.source
    q = load_profile(path, units="mm", dataset="Dataset 2")
    np.testing.assert_allclose(q.x, [0.001, 0.002, 0.003, 0.004])
    with pytest.raises(ValueError, match=r"p\.csv: line 1: no dataset named 'Dataset 3'"):
        load_profile(path, units="mm", dataset="Dataset 3")
    bad = write(tmp_path, "A,,B,\nX,Y,X,Y\n10,80,1,2\n20,,2,3\n40,50,3,4\n", "bad.csv")
    with pytest.raises(ValueError, match=r"bad\.csv: line 4: dataset 'A' has an empty Y cell"):
        load_profile(bad, units="mm")


def test_header_units_and_column_units(tmp_path):
    for head, scale in (("x_m,h_m", 1.0), ("x_cm,h_cm", 1e-2), ("x_mm,h_mm", 1e-3)):
        p = load_profile(write(tmp_path, f"{head}\n1,8\n2,7\n4,5\n"))
        np.testing.assert_allclose(p.x, np.array([1.0, 2.0, 4.0]) * scale)
    p = load_profile(write(tmp_path, "# units: mm\nx,h\n10,80\n20,70\n40,50\n"))
    np.testing.assert_allclose(p.h, EXPECTED_H)
    p = load_profile(write(tmp_path, "# units: cm\n1,8\n2,7\n4,5\n"))
    np.testing.assert_allclose(p.x, EXPECTED_X)
    assert "units" not in p.meta


def test_header_continuation_lines_and_final_time(tmp_path):
    """An indented comment right below a key line continues its value; a blank line or a plain
    free comment ends it. A time_s in words starting with "final" is the final deposit."""
    text = ("# experiment: Someone (2008), a collapse\n#   (J. Things 1, 2-3), final surface\n"
            "# source: a figure\n\n#   not a continuation, a blank line came before\n"
            "# licence: GPL-3.0\n# a free comment\n#   nor this\n"
            "# time_s: final deposit (the flow has stopped)\n# units: m\nx_m,h_m\n0,0.1\n0.1,0.05\n0.2,0\n")
    p = load_profile(write(tmp_path, text))
    assert p.experiment == "Someone (2008), a collapse (J. Things 1, 2-3), final surface"
    assert p.source == "a figure" and p.meta["licence"] == "GPL-3.0"
    assert p.time_s is None and p.meta["time_s_text"] == "final deposit (the flow has stopped)"
    assert "not a continuation" not in json.dumps(p.meta) and "nor this" not in json.dumps(p.meta)
    assert load_profile(write(tmp_path, text), time_s=0.8).time_s == 0.8  # the caller may say when
    with pytest.raises(ValueError, match="time_s must be a finite number of seconds, got 'later'"):
        load_profile(write(tmp_path, "# time_s: later\nx_m,h_m\n0,0.1\n0.1,0.05\n0.2,0\n"))


def test_sort_and_clip_noise(tmp_path):
    p = load_profile(write(tmp_path, "20,70\n10,80\n40,50\n30,60\n"), units="mm", sort=True)
    np.testing.assert_allclose(p.x, [0.01, 0.02, 0.03, 0.04])
    np.testing.assert_allclose(p.h, [0.08, 0.07, 0.06, 0.05])
    p = load_profile(write(tmp_path, "10,80\n20,70\n30,-0.05\n40,0\n"), units="mm", clip_noise=True)
    assert p.h[2] == 0.0 and p.meta["clipped_noise_lines"] == [3]


# --------------------------------------------------------------------------------------------
# Errors name the file and the line
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("text, kw, message", [
    ("x_m,h_m\n0,1\n0.1,abc\n0.2,0\n", {}, r"line 3: column 2 \(h\) is not a number: 'abc'"),
    ("x_m,h_m\n0,1\n0.1,1,5\n0.2,0\n", {}, r"line 3: expected 2 columns \(x,h\), got 3"),
    ("x_m,h_m\n0,1\n0.1\n0.2,0\n", {}, r"line 3: expected 2 columns \(x,h\), got 1"),
    ("x_m,h_m\n0,1\n0.1,nan\n0.2,0\n", {}, r"line 3: column 2 \(h\) is not finite: 'nan'"),
    ("x_m,h_m\n0,1\ninf,1\n0.2,0\n", {}, r"line 3: column 1 \(x\) is not finite: 'inf'"),
    ("# experiment: e\nx_m,h_m\n0,1\n0.2,1\n0.1,0\n", {},
     r"x is not strictly increasing: line 4 \(x = 0\.2 m\) is followed by line 5 .*sort=True"),
    ("x_m,h_m\n0,1\n0.1,1\n0.1,0\n", {}, r"x is not strictly increasing: line 3 .* line 4"),
    ("x_m,h_m\n0,1\n0.1,1\n0.1,0\n", {"sort": True}, r"duplicate x = 0\.1 m at lines 3 and 4"),
    ("x_m,h_m\n0,1\n0.1,-0.0001\n0.2,0\n", {}, r"negative height at line 3 \(h = -0\.0001 m\).*clip_noise=True"),
    ("x_m,h_m\n0,1\n0.1,-0.01\n0.2,0\n", {"clip_noise": True}, r"beyond the noise tolerance .* at line 3"),
    ("x_m,h_m\n0,1\n0.1,0\n", {}, r"2 data row\(s\); at least 3 are needed"),
    ("x_m,h_m\n0,0\n0.1,0\n0.2,0\n", {}, r"h is zero or negative everywhere"),
    ("# units: inch\nx,h\n0,1\n1,1\n2,0\n", {}, r"unknown units 'inch' in the header \(line 1\)"),
    ("0,1\n1,1\n2,0\n", {"units": "in"}, r"unknown units 'in' in the argument units="),
    ("0,1\n1,1\n2,0\n", {}, r"the file has no units .*pass units='m'\|'cm'\|'mm'"),
    ("x_mm,h_mm\n0,1\n1,1\n2,0\n", {"units": "m"}, r"conflicting units: 'mm' in the column names, 'm' in the argument"),
    ("x_mm,h_cm\n0,1\n1,1\n2,0\n", {}, r"line 1: x and h columns have different units"),
    ("dist,height\n0,1\n1,1\n2,0\n", {}, r"line 1: unrecognised column names \['dist', 'height'\]"),
    ("# time_s: 0.5\nx_m,h_m\n0,1\n1,1\n2,0\n", {"time_s": 0.4}, r"time_s=0\.4 contradicts the header \(line 1"),
    ("# time_s: soon\nx_m,h_m\n0,1\n1,1\n2,0\n", {}, r"line 1: time_s must be a finite number"),
    ("# synthetic: maybe\nx_m,h_m\n0,1\n1,1\n2,0\n", {}, r"line 1: synthetic must be true or false"),
    ("# a: 1\n# a: 2\nx_m,h_m\n0,1\n1,1\n2,0\n", {}, r"line 2: header key 'a' repeats line 1"),
    ("0,1\n1,1\n2,0\n", {"units": "m", "dataset": "D"}, r"dataset='D' given but the file has no dataset names"),
    ("# experiment: only a header\n", {}, r"no data rows"),
])
def test_profile_errors(tmp_path, text, kw, message):
    path = write(tmp_path, text, "bad_file.csv", newline="\r\n")
    with pytest.raises(ValueError, match=r"bad_file\.csv: (negative height )?" + message):
        load_profile(path, **kw)


def test_missing_file(tmp_path):
    with pytest.raises(ValueError, match=r"nothere\.csv: no such file"):
        load_profile(tmp_path / "nothere.csv")


def test_profile_dataclass_validation():
    with pytest.raises(ValueError, match="strictly increasing"):
        profile(x=[0.0, 0.02, 0.01, 0.05])
    with pytest.raises(ValueError, match="h must be >= 0"):
        profile(h=[0.04, -0.03, 0.01, 0.0])
    with pytest.raises(ValueError, match="reserved|fields"):
        profile(meta={"units": "mm"}).to_csv("unused.csv")
    with pytest.raises(ValueError, match="meta keys"):
        profile(meta={"a:b": 1}).to_csv("unused.csv")


# --------------------------------------------------------------------------------------------
# Shipped data
# --------------------------------------------------------------------------------------------


def test_manifest_lists_every_file():
    datasets = list_datasets()
    listed = {info.path.resolve() for info in datasets.values()}
    shipped = {p.resolve() for p in DATA.rglob("*") if p.is_file() and p.name not in
               ("README.md", "manifest.json", "generate.py", "__init__.py") and "__pycache__" not in p.parts}
    assert listed == shipped
    for info in datasets.values():
        assert info.kind in ("setup", "experiment", "incline", "scaling_law", "analytic", "synthetic", "flow_rule",
                             "h_stop", "example", "measured", "terrain")
        # a third party's file: whose, what licence
        assert info.kind not in ("measured", "terrain") or (info.source and info.licence)
        assert info.description and "\n" not in info.description
        assert dataset_path(info.name) == info.path
        assert dataset_path(str(info.path.relative_to(data.data_dir()))) == info.path


def test_every_shipped_file_loads():
    for name, info in list_datasets().items():
        if info.kind == "setup":
            setup = load_setup(name)
            assert setup["scene"] in name
        elif info.kind == "experiment":
            from jaxmpm.experiment import Experiment

            assert Experiment.from_toml(info.path).name
        elif info.kind == "scaling_law":
            law = load_scaling_law(info.path)
            assert law.secondary and info.secondary and law.n == 10
        elif info.kind == "analytic":
            header, columns = read_table(info.path)
            assert set(columns) == {"slope_deg", "z_m", "v_m_per_s"}
            assert header["analytic"] is True and header["synthetic"] is False
        elif info.kind == "synthetic":
            loaded = load_front_history(info.path) if "front" in name else load_profile(info.path)
            assert loaded.synthetic and info.synthetic
            assert "synthetic" in loaded.experiment
            assert loaded.source.startswith("python ") and loaded.meta["status"] == 0
            assert set(loaded.meta["parameters"]) >= {"beta", "mu1", "mu2", "I0", "xi", "pc0"}
        elif info.kind == "flow_rule":
            table = load_flow_rule(info.path)
            assert table.n >= 4 and table.slopes.size >= 3 and table.meta["synthetic"] is info.synthetic
        elif info.kind == "h_stop":
            table = load_h_stop(info.path)
            assert table.n >= 3 and table.meta["synthetic"] is info.synthetic and table.secondary is info.secondary
        elif info.kind == "incline":
            incline = load_incline(info.path)
            assert incline.table_file.is_file() and set(incline.keys) <= {"mu1", "mu2", "I0"}
        elif info.kind == "measured":
            p = load_profile(info.path)
            assert not p.synthetic and not info.synthetic and p.n >= 5 and "licence" in p.meta
        elif info.kind == "terrain":
            header, columns = read_table(info.path)
            assert set(columns) == {"x_m", "z_m"} and "licence" in header and not info.synthetic
            terrain = jm.Terrain.from_csv(info.path)
            assert len(terrain.x) == len(columns["x_m"]) >= 2
        else:
            p = load_profile(info.path, units="mm", experiment="S4 beta=0.25 (synthetic, format example)")
            assert p.synthetic and p.n >= 5


def test_synthetic_headers_record_their_command():
    for name, beta in (("synthetic/S4_beta0.25", 0.25), ("synthetic/S4_beta0", 0.0), ("synthetic/S3_10deg", 0.0)):
        p = load_profile(dataset_path(name))
        assert p.source.startswith("python -m jaxmpm run ")
        assert f"--profile-csv experiments_data/{name}.csv" in p.source
        assert p.meta["parameters"]["beta"] == beta
        assert p.time_s == (1.0 if "S3" in name else 0.5)
        assert np.all(p.h >= 0) and p.h.max() > 0.01
    # cohesion shortens the runout (docs/scenes.md S4): a sanity check of the labels, not a result
    dry, wet = load_profile(dataset_path("synthetic/S4_beta0")), load_profile(dataset_path("synthetic/S4_beta0.25"))
    assert wet.x[wet.h > 1e-3].max() < dry.x[dry.h > 1e-3].max()


def test_scaling_laws_match_formulas():
    from jaxmpm.scenes import height_law, runout_law

    glass = load_scaling_law(dataset_path("scaling_laws/runout_glass_beads"))
    sand = load_scaling_law(dataset_path("scaling_laws/runout_sand_lube2005"))
    a = np.array([0.5, 0.7, 1, 1.5, 2, 2.3, 3, 4, 6, 8])
    np.testing.assert_array_equal(glass.a, a)
    np.testing.assert_allclose(glass.runout, np.where(a <= 2.3, 1.2 * a, 1.9 * a ** (2 / 3)), rtol=1e-9)
    np.testing.assert_allclose(glass.height, np.where(a <= 0.7, a, a ** (1 / 3)), rtol=1e-9)
    np.testing.assert_allclose(sand.runout, np.where(a <= 2.3, 1.6 * a, 2.2 * a ** (2 / 3)), rtol=1e-9)
    np.testing.assert_allclose(glass.runout, runout_law(a), rtol=1e-9)
    np.testing.assert_allclose(glass.height, height_law(a), rtol=1e-9)
    assert sand.height is None and glass.secondary and sand.secondary
    assert "Kumar" in glass.source and "1.9 a^(2/3)" in glass.meta["formula_runout"]


def test_bagnold_table_matches_model():
    from jaxmpm.params import DEFAULTS
    from jaxmpm.scenes import S1_PARAMS, bagnold_velocity

    header, cols = read_table(dataset_path("bagnold/bagnold_profiles"))
    params = {**DEFAULTS, **S1_PARAMS}
    for slope in (22.0, 24.0, 26.0, 28.0):
        rows = cols["slope_deg"] == slope
        assert rows.sum() == 21
        np.testing.assert_allclose(cols["v_m_per_s"][rows], bagnold_velocity(cols["z_m"][rows], 0.038, slope, params),
                                   rtol=1e-9, atol=1e-12)
    surface = header["surface_velocity_m_per_s"]
    # docs/model.md section 6's worked example
    assert (round(surface["22"], 3), round(surface["24"], 3), round(surface["28"], 3)) == (0.433, 1.483, 6.116)


def _material(setup):
    return {k: v["value"] for k, v in setup["material"].items() if k in data_param_keys()}


def data_param_keys():
    """The material's keys: a set-up lists the material; μ_w belongs to a scene's walls."""
    from jaxmpm.params import MATERIAL_KEYS

    return MATERIAL_KEYS


def _check_params(setup, scene):
    expected = _material(setup)
    assert set(expected) == set(data_param_keys())
    got = scene.params.to_dict()
    for key, value in expected.items():
        assert math.isclose(got[key], value, rel_tol=1e-7), (setup["scene"], key, got[key], value)
    cfg = scene.config
    numerics = setup["numerics"]
    assert (cfg.transfer, cfg.alpha, cfg.cfl) == (numerics["transfer"]["value"], numerics["alpha"]["value"],
                                                  numerics["cfl"]["value"])
    assert scene.info.ppc == numerics["ppc"]["value"]
    assert scene.info.sampling == numerics["sampling"]["value"]


def _gate_speeds(scene):
    return sorted(w.velocity[1] for w in scene.config.walls if w.velocity[1] != 0)


def test_setups_agree_with_scene_builders():
    """The facts the shipped files state beside the values the builders use (the experiment
    files' equality with the builders is tests/test_experiment.py's)."""
    from jaxmpm import scenes
    from jaxmpm.experiment import shipped_experiment

    s2 = shipped_experiment("gates-collapse")
    scene = scenes.gates_collapse()
    assert _gate_speeds(scene) == [s2.gate_speed] * 2 and s2.gate == "both" and not s2.back_wall
    assert "100 frames at 238.2166843 frames per second" in s2.sources["numerics.t_end"]["note"]
    assert math.isclose(100 / 238.2166843, scene.config.t_end, rel_tol=1e-4)

    s3 = shipped_experiment("slope-collapse")
    assert s3.slope == scenes.slope_collapse().info.slope_deg == 10.0 and s3.gate == "none"
    assert "project choice" in s3.sources["material.pc0"]["source"]
    assert "project choice" in s3.sources["material.xi"]["source"]

    s4 = shipped_experiment("cohesive-collapse")
    assert s4.gate == "front" and s4.gate_speed == 50.0
    assert math.isclose(s4.material["rho"], 0.58 * s4.material["rho_s"])  # packing 0.58 (docs/scenes.md S4)
    assert "beta = 0 and beta = 0.25" in s4.sources["material.beta"]["note"]

    s5 = shipped_experiment("aspect-ratio")
    assert s5.length == 0.05 and s5.height == 0.05 and "project choice" in s5.sources["material.pc0"]["source"]

    s1 = load_setup("setups/S1_incline")
    scene = scenes.incline()
    _check_params(s1, scene)
    assert s1["geometry"]["default_slope_deg"]["value"] == 24.0 and s1["geometry"]["depth_m"]["value"] == 0.038


def test_every_shipped_experiment_value_has_a_source():
    import tomllib

    from jaxmpm.experiment import SHIPPED_EXPERIMENTS

    for file in SHIPPED_EXPERIMENTS.values():
        raw = tomllib.loads((DATA / "experiments" / file).read_text())
        for section in ("geometry", "boundaries", "material", "numerics"):
            for key, value in raw[section].items():
                assert isinstance(value, dict) and value.get("source"), f"{file} [{section}] {key} has no source"


def test_every_setup_number_has_a_source():
    def walk(node, where):
        if isinstance(node, dict):
            if "value" in node:
                assert isinstance(node.get("source"), str) and node["source"], where
                return
            for key, value in node.items():
                walk(value, f"{where}/{key}")
        else:
            assert isinstance(node, (str, list, bool)) or node is None, f"bare number at {where}"

    for name, info in list_datasets().items():
        if info.kind == "setup":
            walk(load_setup(info.path), name)


def test_dataset_lookup_errors(tmp_path, monkeypatch):
    with pytest.raises(FileNotFoundError, match="no shipped dataset 'nope'"):
        dataset_path("nope")
    monkeypatch.setenv("JAXMPM_EXPERIMENTS_DATA", str(tmp_path))
    with pytest.raises(FileNotFoundError, match="has no manifest.json"):
        list_datasets()
    (tmp_path / "manifest.json").write_text(json.dumps({"files": [
        {"name": "mine", "path": "mine.csv", "kind": "example", "description": "d", "synthetic": False,
         "secondary": False}]}))
    with pytest.raises(FileNotFoundError, match="in the manifest but .* is missing"):
        dataset_path("mine")
    write(tmp_path, "0,1\n1,1\n2,0\n", "mine.csv")
    assert load_profile(dataset_path("mine"), units="m").n == 3


def test_data_dir_missing_says_where_it_looked(tmp_path, monkeypatch):
    # jaxmpm/ with no experiments_data/ beside it and no installed jaxmpm.experiments_data
    # (a broken install): the error names both places and the environment variable.
    import jaxmpm.datasets as datasets

    monkeypatch.delenv("JAXMPM_EXPERIMENTS_DATA", raising=False)
    monkeypatch.setattr(datasets, "__file__", str(tmp_path / "site-packages" / "jaxmpm" / "datasets.py"))
    monkeypatch.setattr(datasets, "_installed_data_dir", lambda: None)
    with pytest.raises(FileNotFoundError,
                       match=r"experiments_data/ not found.*source checkout.*not installed.*JAXMPM_EXPERIMENTS_DATA"):
        list_datasets()
