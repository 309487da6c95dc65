"""The 2016 paper (Assawinchaichote & Chayaopas): its printed numbers beside what picdrive computes.

:data:`PRINTED` holds every number the paper prints for its example (Table 1
parameters, gamma/delta/alpha/rho, P, Y_1, Y_2, K_1, K_2, Table 2, the Fig. 7
energy-ratio claim).  :func:`paper_as_printed_model` is the TS model exactly as
printed in section 6 (x1 the electrical speed, torque coefficient
``3/2 P lambda_m/J``, ``N1, N2`` inserted into A_1, A_2 as given);
:func:`claims` computes each claim; :func:`section` writes the report section.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

__all__ = ["PRINTED", "paper_as_printed_model", "printed_checks", "claims", "section"]

PRINTED = {
    "table1": {"P": 2, "L": 0.0018, "R": 0.5, "J": 0.003, "B": 0.0008, "lambda_m": 0.311},
    "gamma": 1.0, "delta": 1.0, "alpha": 2.0, "rho": 1.0, "N": (0.0, 3000.0), "R_uncertainty": 0.1,
    "P_lyap": np.array([[0.2987, 0.0041, 0.0], [0.0041, 1.4933, 0.0], [0.0, 0.0, 1.4933]]),
    "Y1": np.array([[0.2019, 0.0029, -0.0157], [0.0, 0.0190, 0.0054]]),
    "Y2": np.array([[0.0180, 12.2413, 0.0053], [0.2019, 0.0029, 0.8601]]),
    "K1": np.array([[0.9577, 0.0001, -0.0149], [-0.0002, 0.0180, 0.0054]]),
    "K2": np.array([[-0.0722, 11.6125, 0.0050], [0.9577, 0.0001, 0.8159]]),
    "table2": {"fuzzy_settling_s": 0.04, "fuzzy_overshoot_pct": None, "pid_settling_s": 0.22,
               "pid_overshoot_pct": 4.16},
    "pid": {"kp": 0.43, "ki": 2.30, "kd": 0.28},
    "reference_rpm": 2400.0,
    "fig7_ratio": 0.096, "fig7_gamma_text": "sqrt(0.0825) = 0.2864",
}


def paper_as_printed_model(N=None):
    """Section 6's TS model exactly as printed (numbers of Table 1, x1 electrical rad/s).

    ``A_i`` with ``-B/J, 3/2 P/J lambda_m`` in row 1, ``N_i`` in the coupling
    terms; ``B_1 = B_2``, ``Bw`` with ``-P/J``, ``C = diag(1, 0, 0)`` (as the
    1 x 3 output ``x1``), ``H1 = diag(0, -0.1 R/L, -0.1 R/L)``.
    """
    from .tsfuzzy import TSModel
    t = PRINTED["table1"]
    P_, L, R, J, B, lam = t["P"], t["L"], t["R"], t["J"], t["B"], t["lambda_m"]
    N = PRINTED["N"] if N is None else N

    def A(n):
        return np.array([[-B / J, 1.5 * P_ / J * lam, 0.0],
                         [-lam / L, -R / L, -L / L * n],
                         [0.0, L / L * n, -R / L]])
    Bm = np.array([[0.0, 0.0], [1 / L, 0.0], [0.0, 1 / L]])
    Bw = np.array([[0.0, 0.0, -P_ / J], [0.0, 0.1, 0.0], [0.1, 0.0, 0.0]])
    H1 = np.diag([0.0, -0.1 * R / L, -0.1 * R / L])
    return TSModel(A=np.stack([A(N[0]), A(N[1])]), B=np.stack([Bm, Bm]), Bw=Bw,
                   C=np.stack([np.array([[1.0, 0, 0]])] * 2), D=np.zeros((2, 1, 2)), H1=np.stack([H1, H1]),
                   H2=np.zeros((2, 3, 2)), H3=np.zeros((2, 1, 3)), H4=np.zeros((2, 1, 2)), rho=1.0,
                   premise_rad_s=(float(N[0]), float(N[1])),
                   state_names=("omega_e", "i_q", "i_d"), input_names=("v_q", "v_d"),
                   disturbance_names=("w1", "w2", "w3"), output_names=("omega_e",),
                   info={"state_scale": np.array([max(N[1], 1.0), 10.0, 10.0]),
                         "input_scale": np.array([48.0, 48.0])})


def printed_checks(ts=None) -> dict:
    """What the printed P, Y_j, K_j do in the printed model (or ``ts``)."""
    from .fuzzy_hinf import lmi_margins
    ts = paper_as_printed_model() if ts is None else ts
    P, Y1, Y2, K1, K2 = (PRINTED[k] for k in ("P_lyap", "Y1", "Y2", "K1", "K2"))
    Pi = np.linalg.inv(P)
    K_from_Y = [Y1 @ Pi, Y2 @ Pi]
    out = {"K_from_Y": K_from_Y,
           "K_from_Y_max_abs_diff": max(float(np.max(np.abs(K_from_Y[0] - K1))), float(np.max(np.abs(K_from_Y[1] - K2)))),
           "psi1_11": float(2 * (ts.A[0][0] @ P[:, 0])),       # (1,1) entry of A_i P + P A_i^T + B_i Y_j (B row 1 = 0)
           "lmi_margins": lmi_margins(ts, P, [Y1, Y2], PRINTED["gamma"], PRINTED["delta"], PRINTED["alpha"],
                                      PRINTED["rho"], scaled=False)}
    eig = {}
    for name, Ks in (("printed K", [K1, K2]), ("Y P^-1", K_from_Y)):
        for i in range(2):
            for j in range(2):
                eig[f"{name}: A{i+1}+B{i+1}K{j+1}"] = np.linalg.eigvals(ts.A[i] + ts.B[i] @ Ks[j])
    out["closed_loop_eigs"] = eig
    out["max_real_eig_printed_K"] = max(float(np.max(e.real)) for k, e in eig.items() if k.startswith("printed"))
    out["max_real_eig_Y_P_inv"] = max(float(np.max(e.real)) for k, e in eig.items() if k.startswith("Y P"))
    return out
