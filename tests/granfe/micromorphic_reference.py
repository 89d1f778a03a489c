"""The isotropic micromorphic moduli built independently of granfe (from Kronecker deltas,
as Tardigrade's ``formIsotropicA..D``), for the tests of both micromorphic models."""

import numpy as np


def tensors(p, d):
    """A, B, C, D of Eringen / Tardigrade ``formIsotropicA..D`` as full arrays (built from
    Kronecker deltas, independently of the module's contractions)."""
    eye = np.eye(d)

    def e2(s):
        return np.einsum(f"{s[:2]},{s[3:5]}->klmn", eye, eye)

    def e3(s):
        i, j, k = s.split()
        return np.einsum(f"{i},{j},{k}->klmnpq", eye, eye, eye)

    sym = e2("km ln") + e2("kn lm")
    A = p["lam"] * e2("kl mn") + p["mu"] * sym
    B = ((p["eta"] - p["tau"]) * e2("kl mn") + p["kappa"] * e2("km ln") + p["nu"] * e2("kn lm")
         - p["sigma"] * sym)
    D = p["tau"] * e2("kl mn") + p["sigma"] * sym
    t = [p[f"tau{i}"] for i in range(1, 12)]
    C = (t[0] * (e3("kl mn pq") + e3("kq lm np")) + t[1] * (e3("kl mp nq") + e3("km lq np"))
         + t[2] * e3("kl mq np") + t[3] * e3("kn lm pq") + t[4] * (e3("km ln pq") + e3("kp lm nq"))
         + t[5] * e3("km lp nq") + t[6] * e3("kn lp mq") + t[7] * (e3("kp lq mn") + e3("kq ln mp"))
         + t[8] * e3("kn lq mp") + t[9] * e3("kp ln mq") + t[10] * e3("kq lp mn"))
    return A, B, C, D
