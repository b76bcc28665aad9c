r"""Levenberg–Marquardt with and without geodesic acceleration on the S4 fit at dx = 4 mm
(issue 44, item 3): docs/results/geodesic_lm_4mm.json.

Geodesic acceleration (Transtrum & Sethna 2012, arXiv:1201.5885) adds to LM's step v the
second-order correction a/2, a = −(JᵀJ + λD)⁻¹ Jᵀ r_vv, with the residuals' second directional
derivative r_vv ≈ (2/h) [(r(z + h v) − r(z))/h − J v] (h = 0.1): one more forward run an
iteration. The correction is taken where 2‖a‖/‖v‖ ≤ 0.75 (their α), else the plain step.
Everything else is the library's LM (``calibration.optim.lm.propose`` and ``judge``), one start,
one core, from the two coarse minima ``python -m calibration fit ... --coarse 2`` refines (the
case of docs/performance.md, "A fit at dx = 4 mm: where the time goes"):

    python -m jaxmpm run cohesive-collapse --dx 0.004 --set pc0=500 --set xi=50 --set beta=0.3 \
        --set mu1=0.55 --profile-csv twin4mm.csv
    taskset -c 0 python docs/scripts/geodesic_lm.py twin4mm.csv   # about 16 minutes
"""

import json
import pathlib
import sys
import time

import jax.numpy as jnp
import numpy as np

import calibration as cal
from calibration.optim.lm import LAM0, LMOptions, judge, propose
from calibration.problem.bounds import MAX_STEP
from jaxmpm.scenes import build_scene

ROOT = pathlib.Path(__file__).resolve().parents[2]
#: The two coarse minima (8 mm) the fine stage starts from (docs/results/fit_4mm_2026-12-06.json).
STARTS = ((0.5437837839126587, 0.3526687026023865), (0.40797165036201477, 0.39925453066825867))
H, ALPHA, STEPS, LOSS_DONE = 0.1, 0.75, 24, 1e-10


def lm(objective, start, geodesic):
    """LM from ``start`` until the loss is below ``LOSS_DONE`` (the twin is noise-free; the
    fit's round-off stop lands near 1e-11) or LM stops: one record per iteration."""
    bounds = objective.bounds

    def jacobian(z):
        r, Jz, _, pred = objective.residuals_and_jacobian_z(jnp.asarray(z, objective.dtype))
        return np.asarray(r, float), np.asarray(Jz, float), int(pred["status"])

    def residuals(z):
        return np.asarray(objective.residuals(np.asarray(bounds.to_physical(jnp.asarray(z)), float))[0], float)

    def theta(z):
        return np.asarray(bounds.to_physical(jnp.asarray(z)), float)

    clock = time.perf_counter()
    z = np.asarray(bounds.to_unconstrained(np.array(start)), float)
    r, Jz, _ = jacobian(z)
    lam, rejections, log = LAM0, 0, []
    for it in range(STEPS):
        delta, promised = propose(r[None], Jz[None], np.array([lam]))
        delta, record = delta[0], {}
        if geodesic:
            r_vv = (2.0 / H) * ((residuals(z + H * delta) - r) / H - Jz @ delta)
            A = Jz.T @ Jz
            d = np.maximum(np.diag(A), 1e-12 * np.diag(A).max())
            a = -np.linalg.solve(A + lam * np.diag(d), Jz.T @ r_vv)
            ratio = 2.0 * np.sqrt(np.sum(d * a * a) / np.sum(d * delta * delta))
            record = {"ratio": float(ratio), "corrected": bool(ratio <= ALPHA)}
            if ratio <= ALPHA:
                delta = delta + 0.5 * a
                delta = delta * min(1.0, MAX_STEP / max(np.max(np.abs(delta)), 1e-300))
        r_t, Jz_t, status = jacobian(z + delta)
        accepted, lam_, rej_, done, message = judge(
            np.array([r @ r]), theta(z)[None], np.array([r_t @ r_t]), theta(z + delta)[None], np.array([status == 0]),
            promised, np.array([lam]), np.array([rejections]), r.size, LMOptions())
        lam, rejections = float(lam_[0]), int(rej_[0])
        if accepted[0]:
            z, r, Jz = z + delta, r_t, Jz_t
        log.append({"iteration": it + 1, "loss": float(r @ r), "accepted": bool(accepted[0]), "lam": lam,
                    "theta": theta(z).tolist(), "wall_s": time.perf_counter() - clock, **record})
        print(json.dumps(log[-1]), flush=True)
        if r @ r < LOSS_DONE or done[0]:
            break
    return log


def main(twin_csv):
    scene = build_scene("cohesive-collapse", dx=0.004, values={"pc0": 500.0, "xi": 50.0})
    objective = cal.Objective(scene, ("beta", "mu1"), profile=cal.load_profile(twin_csv))
    out = {"case": "S4 (beta, mu1) at dx = 4 mm, noise-free twin at (0.3, 0.55), one core",
           "h": H, "alpha": ALPHA, "loss_done": LOSS_DONE, "runs": {}}
    for i, start in enumerate(STARTS):
        for geodesic in (False, True):
            log = lm(objective, start, geodesic)
            out["runs"][f"start{i}_{'geodesic' if geodesic else 'plain'}"] = {
                "start": list(start), "iterations": len(log), "wall_s": log[-1]["wall_s"],
                "final_loss": log[-1]["loss"], "final_theta": log[-1]["theta"], "log": log}
    (ROOT / "docs" / "results" / "geodesic_lm_4mm.json").write_text(json.dumps(out, indent=1))
    for name, run in out["runs"].items():
        print(name, run["iterations"], f"{run['wall_s']:.0f} s", f"{run['final_loss']:.2e}")


if __name__ == "__main__":
    main(sys.argv[1])
