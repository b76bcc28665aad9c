r"""LM's two models of the curvature, measured on fits a user runs: ``calibration fit --lm-model
gauss-newton`` (JᵀJ) against ``--lm-model adaptive`` (JᵀJ plus NL2SOL's secant estimate of
Σ rᵢ ∇²rᵢ where that forecast the last step better; ``calibration.optim.lm``), each fit one
start, one worker, both models on the same machine at the same time (two cores).

The cases:

- ``twin``: S4's (β, μ1) at dx = 8 mm from (0.1, 0.5), its data the model's own deposit at
  (0.25, 0.382): the residuals vanish at the minimum, where Gauss–Newton is at its best.
- ``bui``: μ1 of the aluminium bars (S7, Bui et al. 2008's measured deposit) from 0.30, at the
  default dx = H/16: a real measurement, fitted to 2.5 % of its height. (From 0.45 both models
  end after three iterations at 0.445, a local minimum whose misfit is about twice the fit's at
  0.36, and from 0.6 after two at 0.598; the verdict refuses both points. Those are starts for
  the global search, not for LM.)
- ``W2cm_plain``, ``W2cm_walls``, ``W4cm_walls``: μ1 of the 3D channel deposits of
  docs/invariance.md (S4 between walls with μ_w = 0.3, dx = 4 mm) fitted by 2D without and with
  the side-wall term, from 0.45: data the 2D model cannot reach (χ² 4 to 8 times its limit),
  where Gauss–Newton's fits ran out of their 25 iterations.

    python docs/scripts/lm_models.py            # about 40 minutes on two cores (the 3D runs: 3.5 of them)
    python docs/scripts/lm_models.py --plot     # the figure again from the JSON

Each fit's JSON is kept in ``--out`` (a rerun resumes); the summary goes to
docs/results/lm_models.json and the figure (the loss against the iteration) to
docs/figures/lm_models.png.
"""

import argparse
import json
import pathlib
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor

import h5py
import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "docs" / "scripts"))
from width_invariance import MU_W, SCENE  # noqa: E402  (the channel study's scene and walls)

MODELS = ("gauss-newton", "adaptive")
S4 = ["cohesive-collapse", "--set", "pc0=500", "--set", "xi=50", "--dx", "0.008"]


def _json(command, path: pathlib.Path):
    """``command``'s JSON, kept in ``path``."""
    if not path.exists():
        print("running", " ".join(command[2:]), file=sys.stderr, flush=True)
        done = subprocess.run([sys.executable, *command], capture_output=True, text=True, cwd=ROOT)
        if not done.stdout.strip():
            raise RuntimeError(f"{' '.join(command)} failed:\n{done.stderr[-2000:]}")
        path.write_text(done.stdout)
    return json.loads(path.read_text())


def data(folder: pathlib.Path) -> dict[str, list[str]]:
    """Every case's ``calibration fit`` arguments (its data made first where it is made here)."""
    twin_csv, cases = folder / "twin.csv", {}
    _json(["-m", "jaxmpm", "run", *S4, "--set", "beta=0.25", "--set", "mu1=0.382", "--no-progress", "--json",
           "--profile-csv", str(twin_csv)], folder / "twin_run.json")
    cases["twin"] = ["--scene", *S4, "--data", str(twin_csv), "--fit", "beta,mu1", "--init", "beta=0.1",
                     "--init", "mu1=0.5"]
    cases["bui"] = ["--scene", "aluminium-bars", "--data", "experiments_data/bui2008/bui2008_final_surface.csv",
                    "--fit", "mu1", "--init", "mu1=0.30"]
    for width in (0.02, 0.04):
        walls, name = ["--side-walls", f"{width},{MU_W}"], f"W{width * 100:g}cm"
        csv = folder / f"{name}_3d.csv"
        _json(["-m", "jaxmpm", "run", *SCENE, "--dim", "3", "--width", str(width), "--ppc", "2", *walls,
               "--no-progress", "--json", "--profile-csv", str(csv)], folder / f"{name}_3d.json")
        common = ["--scene", *SCENE, "--data", str(csv), "--fit", "mu1", "--init", "mu1=0.45"]
        if width == 0.02:
            cases[f"{name}_plain"] = common
        cases[f"{name}_walls"] = [*common, *walls]
    return cases


def fit(folder: pathlib.Path, name: str, arguments: list[str], model: str) -> dict:
    h5 = folder / f"{name}_{model}.h5"
    out = _json(["-m", "calibration", "fit", *arguments, "--lm-model", model, "--workers", "1", "--no-progress",
                 "--json", "--out", str(h5), "--overwrite"], folder / f"{name}_{model}.json")
    with h5py.File(h5, "r") as f:
        loss = np.asarray(f["history/loss"], float)
        accepted = np.asarray(f["history/accepted"], bool)
    return {"keys": list(out["params"]), "theta": out["params"], "loss": out["loss"], "iterations": out["iterations"],
            "wall_s": out["wall_s"], "message": out["message"], "verdict": out["verdict"]["verdict"],
            "statement": out["statement"], "loss_history": loss.tolist(), "accepted": accepted.tolist()}


def plot(summary: dict, path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cases = summary["cases"]
    fig, axes = plt.subplots(1, len(cases), figsize=(3.2 * len(cases), 3.4))
    for ax, (name, case) in zip(axes, cases.items()):
        best = min(min(case[m]["loss_history"]) for m in MODELS)
        for model, color in zip(MODELS, ("C0", "C3")):
            loss = np.minimum.accumulate(np.asarray(case[model]["loss_history"]))
            ax.semilogy(np.arange(1, loss.size + 1), loss / best - 1 + 1e-12, "o-", ms=3, color=color,
                        label=f"{model}: {case[model]['iterations']} it, {case[model]['wall_s']:.0f} s")
        ax.set(title=name, xlabel="iteration (model runs)", ylim=(1e-10, None))
        ax.legend(fontsize=7)
    axes[0].set_ylabel("loss / lowest loss − 1 (accepted points)")
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main(argv=None):
    parser = argparse.ArgumentParser()
    parser.add_argument("--out", default="/tmp/lm_models")
    parser.add_argument("--plot", action="store_true", help="only the figure, from the results' JSON")
    parser.add_argument("--jobs", type=int, default=2, help="fits at a time (one core each)")
    args = parser.parse_args(argv)
    results = ROOT / "docs" / "results" / "lm_models.json"
    figure = ROOT / "docs" / "figures" / "lm_models.png"
    if not args.plot:
        folder = pathlib.Path(args.out)
        folder.mkdir(parents=True, exist_ok=True)
        cases = data(folder)
        jobs = [(name, model) for name in cases for model in MODELS]
        with ThreadPoolExecutor(args.jobs) as pool:
            fits = dict(zip(jobs, pool.map(lambda job: fit(folder, job[0], cases[job[0]], job[1]), jobs)))
        summary = {"note": __doc__.split("\n\n")[0], "cases": {
            name: {"arguments": cases[name], **{model: fits[name, model] for model in MODELS}} for name in cases}}
        results.write_text(json.dumps(summary, indent=1) + "\n")
    summary = json.loads(results.read_text())
    for name, case in summary["cases"].items():
        for model in MODELS:
            c = case[model]
            print(f"{name:11s} {model:13s} {c['iterations']:3d} it {c['wall_s']:6.0f} s loss {c['loss']:.6g} "
                  f"{c['theta']} {c['message'][:70]}")
    plot(summary, figure)


if __name__ == "__main__":
    main()
