r"""Levenberg–Marquardt with a structured secant term for large residuals, against plain LM, on a
fit with model error (a prototype, not the library's LM). docs/results/secant_lm_width.json holds
two ``secant`` runs of this script (4 and 2 cm) beside plain LM's histories from the same fits
made by ``calibration fit`` in ``width_invariance.py``.

Where the model cannot reach the data (2D fitted to 3D deposits, docs/invariance.md), the
residuals stay large and the loss's curvature is JᵀJ + Σ r_i ∇²r_i, whose second term is
negative here: Gauss–Newton's JᵀJ overstates the curvature, and its steps fall short of the
minimum by a factor that does not shrink (plain LM crept 0.001 a step for 25 iterations). The
secant term S of Dennis, Gay & Welsch (1981, NL2SOL) estimates Σ r_i ∇²r_i from successive
Jacobians: after an accepted step s, y♯ = J₊ᵀ r₊ − Jᵀ r₊ and y = J₊ᵀ r₊ − Jᵀ r, S sized by
min(1, |sᵀy♯| / |sᵀSs|) and updated so that S s = y♯. The step solves (JᵀJ + S + λD) δ = −Jᵀr
where JᵀJ + S is positive definite, else the Gauss–Newton step. Everything else is the library's
LM (``propose`` for the promise, ``judge``). μ1 alone, 2D with side walls, dx = 4 mm, from 0.45:

    python docs/scripts/width_invariance.py          # makes the 3D deposits in /tmp/width_invariance
    taskset -c 0 python docs/scripts/secant_lm.py secant 0.04 /tmp/width_invariance/W4cm_3d.csv
    taskset -c 0 python docs/scripts/secant_lm.py plain 0.04 /tmp/width_invariance/W4cm_3d.csv

One JSON line an iteration; about 7 s an iteration on one core.
"""

import json
import sys
import time

import jax.numpy as jnp
import numpy as np

import calibration as cal
from calibration.optim.lm import LAM0, LMOptions, judge, propose
from calibration.problem.bounds import MAX_STEP
from jaxmpm import SideWalls
from jaxmpm.scenes import build_scene

mode, W, csv = sys.argv[1], float(sys.argv[2]), sys.argv[3]
scene = build_scene("cohesive-collapse", dx=0.004, values={"beta": 0.25, "pc0": 500.0, "xi": 50.0},
                    side_walls=SideWalls(W, 0.3))
obj = cal.Objective(scene, ("mu1",), profile=cal.load_profile(csv))
b = obj.bounds

def jac(z):
    r, Jz, _, pred = obj.residuals_and_jacobian_z(jnp.asarray(z, obj.dtype))
    return np.asarray(r, float), np.asarray(Jz, float), int(pred["status"])



def th(z):
    return np.asarray(b.to_physical(jnp.asarray(z)), float)


t0 = time.perf_counter()
z = np.asarray(b.to_unconstrained(np.array([0.45])), float)
r, J, _ = jac(z)
n = z.size
S = np.zeros((n, n))
lam, rej = LAM0, 0
for it in range(25):
    A = J.T @ J
    d = np.maximum(np.diag(A), 1e-12 * np.diag(A).max())
    g = J.T @ r
    use_S = mode == "secant" and np.all(np.linalg.eigvalsh(A + S) > 0.05 * np.diag(A).min())
    H = A + S if use_S else A
    delta = -np.linalg.solve(H + lam * np.diag(d), g)
    delta *= min(1.0, MAX_STEP / max(np.max(np.abs(delta)), 1e-300))
    _, promised = propose(r[None], J[None], np.array([lam]))
    r_t, J_t, st = jac(z + delta)
    acc, lam_, rej_, done, msg = judge(np.array([r @ r]), th(z)[None], np.array([r_t @ r_t]), th(z + delta)[None],
                                       np.array([st == 0]), promised, np.array([lam]), np.array([rej]), r.size,
                                       LMOptions())
    lam, rej = float(lam_[0]), int(rej_[0])
    if acc[0]:
        s = delta
        y = J_t.T @ r_t - g
        y_sharp = J_t.T @ r_t - J.T @ r_t
        ys = float(y @ s)
        if mode == "secant" and abs(ys) > 1e-300:
            tau = min(1.0, abs(s @ y_sharp) / max(abs(s @ S @ s), 1e-300)) if np.any(S) else 1.0
            S = tau * S
            w = y_sharp - S @ s
            S = S + (np.outer(w, y) + np.outer(y, w)) / ys - (w @ s) * np.outer(y, y) / ys**2
        z, r, J = z + delta, r_t, J_t
    print(json.dumps({"it": it + 1, "mu1": float(th(z)[0]), "loss": float(r @ r), "acc": bool(acc[0]), "lam": lam,
                      "S": S.tolist(), "used_S": bool(use_S), "wall": round(time.perf_counter() - t0, 1)}), flush=True)
    if done[0]:
        print("done", msg, flush=True)
        break
