"""Continuum stress measures from contact forces (seed 002 eq. 1-15).

Conventions (all arrays plain numpy, SI units):
``x`` (n, 3) centres [m]; ``pairs`` (m, 2) int contact pairs (i, j); ``force`` (m, 3) [N]
the force ON i BY j; branch vector ``b = x[j] - x[i]`` [m]; contact points ``xc`` (m, 3) [m]
(default: on the line of centres, at i's surface moved back by half the overlap).
Stresses are tension-positive [Pa]; in 2D (domains with 2 axes) volumes are areas times a
unit thickness, as for the disks of `dem.state`. For the unsymmetric tensors the FIRST index
is the branch/normal index and the second the force index, so a traction is
``t_l = n_k sigma_kl`` (seed 002 eq. 8, 13).

Micromorphic measures over an averaging domain Omega (seed 002 §2) split into RVEs:

* RVE granular stress   sigma'_kl = 1/V_R sum_c (f_k b_l + f_l b_k)/2            (eq. 1)
* micro-stress          s_kl      = 1/V sum_R sigma'_kl V_R                       (eq. 2, 5)
* couple stress         m_klm     = 1/V sum_R sigma'_kl xi_m V_R                  (eq. 3, 6)
* Cauchy stress from the balance of first moment of momentum (eq. 10-12)
      sigma_mk = s_mk - D_mk - 1/V sum_R M_R (g_k - a'_k) xi_m
  with the couple-stress divergence D_mk = 1/V int_Gamma m_lkm n_l da, discretised as
  in eq. 12 by the RVE faces on the domain surface: sum sigma'_lk xi_m n_l a_R.
* granular stress       sigma^G_kl = 1/V sum_c b_k f_l                            (eq. 13)

xi is the RVE centre relative to the domain centre, M_R the mass of the particles whose
centres lie in RVE R and a'_R their mean acceleration relative to the domain's.

Caveat, derived here and tested: for a homogeneous sigma' the face sum of eq. 12 gives
D_mk = (1 - 1/n_m) s_mk with n_m RVEs along axis m, i.e. sigma = s / n_m, a value set by
the RVE split, not by the material (the reduction of sigma against s reported in the
paper's Fig. 5 may be this). ``couple_flux="none"`` drops D (sigma = s for a homogeneous
state without gravity and acceleration).
"""

from __future__ import annotations

import csv
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

__all__ = ["AveragingDomain", "EmptyRVEError", "MicromorphicStress", "contact_points", "record_frames",
           "couple_measures", "love_weber_stress", "mean_stress", "micromorphic_stress",
           "octahedral_shear", "StressRecorder"]


class EmptyRVEError(ValueError):
    """An RVE of the averaging domain holds no contact point (its stress is undefined)."""


def _as(name, a, shape, dtype=np.float64):
    a = np.asarray(a, dtype=dtype)
    if a.ndim != len(shape) or any(s is not None and s != t for s, t in zip(shape, a.shape, strict=False)):
        want = "(" + ", ".join("n" if s is None else str(s) for s in shape) + ")"
        raise ValueError(f"{name} must have shape {want}, got {a.shape}")
    if dtype is np.float64 and not np.all(np.isfinite(a)):
        raise ValueError(f"{name} has non-finite entries")
    return a


def _contacts(x, pairs, force):
    x = _as("x", x, (None, 3))
    pairs = _as("pairs", pairs, (None, 2), np.int64)
    force = _as("force", force, (len(pairs), 3))
    if len(pairs) and (pairs.min() < 0 or pairs.max() >= len(x)):
        raise ValueError(f"pairs must index particles 0..{len(x) - 1}")
    return x, pairs, force


def contact_points(x, radius, pairs) -> np.ndarray:
    """Default contact points (m, 3) [m]: x_i + (r_i - overlap/2) n, n from i to j."""
    d = x[pairs[:, 1]] - x[pairs[:, 0]]
    dist = np.linalg.norm(d, axis=1)
    if np.any(dist == 0):
        raise ValueError("coincident centres in a contact pair; contact normal undefined")
    overlap = radius[pairs[:, 0]] + radius[pairs[:, 1]] - dist
    return x[pairs[:, 0]] + d * ((radius[pairs[:, 0]] - 0.5 * overlap) / dist)[:, None]


def love_weber_stress(x, pairs, force, volume: float, contact_mask=None,
                      symmetric: bool = True) -> np.ndarray:
    """Love-Weber stress (3, 3) [Pa] = 1/V sum_c b_k f_l over the contacts in ``contact_mask``
    (bool (m,); e.g. contact points inside any region of volume ``volume`` [m^3]);
    symmetrised (eq. 1) unless ``symmetric=False`` (eq. 13)."""
    x, pairs, force = _contacts(x, pairs, force)
    if not volume > 0:
        raise ValueError(f"volume must be > 0, got {volume!r}")
    if contact_mask is not None:
        pairs, force = pairs[contact_mask], force[contact_mask]
    b = x[pairs[:, 1]] - x[pairs[:, 0]]
    t = np.einsum("ck,cl->kl", b, force) / volume
    return 0.5 * (t + t.T) if symmetric else t


@dataclass(frozen=True, eq=False)
class AveragingDomain:
    """Axis-aligned box ``[lo, hi]`` [m] (2 or 3 axes) split into ``divisions`` equal RVEs.

    For a domain moving with a set of particles, rebuild it each time with `around`.
    """

    lo: tuple
    hi: tuple
    divisions: tuple = (1, 1, 1)
    dim: int = field(init=False)

    def __post_init__(self):
        lo, hi = np.asarray(self.lo, float).ravel(), np.asarray(self.hi, float).ravel()
        if lo.size not in (2, 3) or hi.size != lo.size:
            raise ValueError(f"lo and hi must both have 2 or 3 entries, got {lo.size}, {hi.size}")
        if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))) or np.any(hi <= lo):
            raise ValueError(f"domain must have hi > lo on every axis (zero volume otherwise); "
                             f"got lo={lo.tolist()}, hi={hi.tolist()}")
        div = tuple(int(k) for k in np.ravel(self.divisions))[:lo.size]
        if len(div) != lo.size or min(div) < 1:
            raise ValueError(f"divisions must be {lo.size} integers >= 1, got {self.divisions!r}")
        object.__setattr__(self, "dim", lo.size)
        object.__setattr__(self, "lo", tuple(lo))
        object.__setattr__(self, "hi", tuple(hi))
        object.__setattr__(self, "divisions", div)

    @classmethod
    def around(cls, x, radius, divisions, pad: float = 0.0, dim: int = 3):
        """Bounding box of particles ``x`` (k, 3) with radii (k,), grown by ``pad`` [m]."""
        if len(x) == 0:
            raise ValueError("around() needs at least one particle")
        r = np.asarray(radius)[:, None]
        return cls(tuple((x - r).min(axis=0)[:dim] - pad), tuple((x + r).max(axis=0)[:dim] + pad),
                   divisions)

    @property
    def volume(self) -> float:
        return float(np.prod(np.subtract(self.hi, self.lo)))

    @property
    def n_rve(self) -> int:
        return int(np.prod(self.divisions))

    @property
    def centre(self) -> np.ndarray:
        c = np.zeros(3)
        c[:self.dim] = 0.5 * (np.add(self.lo, self.hi))
        return c

    @property
    def spacing(self) -> np.ndarray:
        return np.subtract(self.hi, self.lo) / np.asarray(self.divisions)

    def rve_centres(self) -> np.ndarray:
        """(n_rve, 3) RVE centres [m], C order over the divisions."""
        axes = [self.lo[a] + (np.arange(k) + 0.5) * self.spacing[a]
                for a, k in enumerate(self.divisions)]
        grid = np.meshgrid(*axes, indexing="ij")
        c = np.zeros((self.n_rve, 3))
        c[:, :self.dim] = np.stack([g.ravel() for g in grid], axis=1)
        return c

    def locate(self, p) -> np.ndarray:
        """RVE index (k,) of points ``p`` (k, 3); -1 outside the half-open box [lo, hi)."""
        q = (np.asarray(p)[:, :self.dim] - np.asarray(self.lo)) / self.spacing
        ijk = np.floor(q).astype(np.int64)
        inside = np.all((ijk >= 0) & (ijk < np.asarray(self.divisions)), axis=1)
        flat = np.ravel_multi_index(tuple(np.clip(ijk, 0, None).T), self.divisions, mode="clip")
        return np.where(inside, flat, -1)


@dataclass(frozen=True, eq=False)
class MicromorphicStress:
    """Stress measures of one averaging domain (see the module docstring for definitions).

    Tensors (3, 3) [Pa]: ``s``, ``sigma`` (all terms), ``sigma_no_spin`` (without the
    micro-spin inertia), ``sigma_no_couples`` (without spin inertia and body couple),
    ``sigma_G``; ``m`` (3, 3, 3) [Pa m]; per RVE: ``rve_stress`` (R, 3, 3), ``rve_contacts``
    (R,), ``rve_mass`` (R,) [kg], ``xi`` (R, 3) [m]; the terms ``couple_flux``,
    ``body_couple``, ``spin_inertia`` (3, 3) [Pa] of eq. 10-12; ``volume`` [m^3].
    """

    s: np.ndarray
    m: np.ndarray
    sigma: np.ndarray
    sigma_no_spin: np.ndarray
    sigma_no_couples: np.ndarray
    sigma_G: np.ndarray
    rve_stress: np.ndarray
    rve_contacts: np.ndarray
    rve_mass: np.ndarray
    xi: np.ndarray
    couple_flux: np.ndarray
    body_couple: np.ndarray
    spin_inertia: np.ndarray
    volume: float

    @property
    def xi_length(self) -> float:
        """Mean |xi| over the RVEs [m], the length normalising couple stresses (eq. 14-15)."""
        return float(np.linalg.norm(self.xi, axis=1).mean())

    def measures(self) -> dict[str, float]:
        """Mean stress and octahedral shear [Pa] of each stress, couple measures [Pa]."""
        out = {}
        for name in ("s", "sigma", "sigma_no_spin", "sigma_no_couples", "sigma_G"):
            t = getattr(self, name)
            out[f"p_{name}"], out[f"tau_{name}"] = mean_stress(t), octahedral_shear(t)
        p_c, tau_c = couple_measures(self.m)
        ell = self.xi_length
        out["p_couple_per_xi"] = p_c / ell if ell > 0 else 0.0
        out["tau_couple_per_xi"] = tau_c / ell if ell > 0 else 0.0
        out["n_contacts"] = int(self.rve_contacts.sum())
        out["empty_rves"] = int((self.rve_contacts == 0).sum())
        return out


def mean_stress(t) -> float:
    """P = tr(t)/3 [Pa] (tension positive)."""
    return float(np.trace(t) / 3.0)


def octahedral_shear(t) -> float:
    """tau_oct = sqrt(dev t : dev t / 3) [Pa]; equals sqrt(2 J2 / 3) for symmetric t."""
    dev = np.asarray(t) - mean_stress(t) * np.eye(3)
    return float(np.sqrt(np.sum(dev * dev) / 3.0))


def couple_measures(m) -> tuple[float, float]:
    """Couple-stress measures of m_klm (3, 3, 3) [Pa m] (seed 002 eq. 14-15).

    p^c_m = m_aam / 3 (a vector); returns |p^c| and tau^c = sqrt(dev m : dev m / 3) with
    dev m_klm = m_klm - p^c_m delta_kl.
    """
    m = np.asarray(m)
    pc = np.einsum("aam->m", m) / 3.0
    dev = m - np.einsum("kl,m->klm", np.eye(3), pc)
    return float(np.linalg.norm(pc)), float(np.sqrt(np.sum(dev * dev) / 3.0))


def _rve_sums(domain, x, pairs, force, xc):
    """Per-RVE sums of sym(f b) and contact counts; unsymmetric b f sum over the domain."""
    rve = domain.locate(xc)
    inside = rve >= 0
    b = x[pairs[inside, 1]] - x[pairs[inside, 0]]
    fb = np.einsum("ck,cl->ckl", force[inside], b)
    sym = np.zeros((domain.n_rve, 3, 3))
    np.add.at(sym, rve[inside], 0.5 * (fb + fb.transpose(0, 2, 1)))
    count = np.bincount(rve[inside], minlength=domain.n_rve)
    return sym, count, np.einsum("ck,cl->kl", b, force[inside])


def _face_flux(domain, rve_stress, xi) -> np.ndarray:
    """D_mk = 1/V sum over RVE faces on the domain surface of sigma'_lk xi_m n_l a (eq. 12)."""
    S = rve_stress.reshape(*domain.divisions, 3, 3)
    X = xi.reshape(*domain.divisions, 3)
    D = np.zeros((3, 3))
    for ax in range(domain.dim):
        area = domain.volume / domain.n_rve / domain.spacing[ax]
        for end, sign in ((-1, 1.0), (0, -1.0)):
            s_face, x_face = np.take(S, end, axis=ax), np.take(X, end, axis=ax)
            D += sign * area * np.einsum("rk,rm->mk", s_face[..., ax, :].reshape(-1, 3),
                                         x_face.reshape(-1, 3))
    return D / domain.volume


def micromorphic_stress(domain: AveragingDomain, x, radius, pairs, force, mass=None, *,
                        accel=None, gravity=(0.0, 0.0, 0.0), xc=None,
                        couple_flux: str = "faces", on_empty: str = "raise"):
    """Micromorphic stress measures of ``domain`` (seed 002 eq. 1-13).

    Args:
        x (n, 3), radius (n,), pairs (m, 2), force (m, 3): see the module docstring.
        mass: (n,) [kg], needed for the body couple and micro-spin inertia terms.
        accel: (n, 3) particle accelerations [m/s^2] (e.g. (v - v_prev)/dt), or None (0).
        gravity: (3,) [m/s^2]; xc: (m, 3) contact points or None for the default.
        couple_flux: ``"faces"`` (eq. 12 as written) or ``"none"`` (see module caveat).
        on_empty: ``"raise"`` an `EmptyRVEError` naming RVEs without contacts, or
            ``"zero"``: such RVEs have zero stress (a loose region carries none).

    Returns:
        `MicromorphicStress`.
    """
    x, pairs, force = _contacts(x, pairs, force)
    radius = _as("radius", radius, (len(x),))
    if couple_flux not in ("faces", "none"):
        raise ValueError(f"couple_flux must be 'faces' or 'none', got {couple_flux!r}")
    if on_empty not in ("raise", "zero"):
        raise ValueError(f"on_empty must be 'raise' or 'zero', got {on_empty!r}")
    xc = contact_points(x, radius, pairs) if xc is None else _as("xc", xc, (len(pairs), 3))
    owner = domain.locate(x)
    if not np.any(owner >= 0):
        raise ValueError(f"averaging domain lo={list(domain.lo)}, hi={list(domain.hi)} holds no "
                         f"particle centre (particles span {x.min(0).tolist()} .. "
                         f"{x.max(0).tolist()})")
    sym, count, bf = _rve_sums(domain, x, pairs, force, xc)
    if on_empty == "raise" and np.any(count == 0):
        empty = np.flatnonzero(count == 0)
        raise EmptyRVEError(f"{empty.size} of {domain.n_rve} RVEs hold no contact point "
                            f"(flat indices {empty[:10].tolist()}...); use larger RVEs, fewer "
                            f"divisions, or on_empty='zero'")
    v_rve = domain.volume / domain.n_rve
    rve_stress = sym / v_rve
    xi = domain.rve_centres() - domain.centre
    s = rve_stress.sum(axis=0) * v_rve / domain.volume
    m = np.einsum("rkl,rm->klm", rve_stress, xi) * v_rve / domain.volume
    flux = _face_flux(domain, rve_stress, xi) if couple_flux == "faces" else np.zeros((3, 3))
    body, spin, rve_mass = _inertia_terms(domain, owner, mass, accel, gravity, xi, len(x))
    return MicromorphicStress(
        s=s, m=m, sigma=s - flux - body + spin, sigma_no_spin=s - flux - body,
        sigma_no_couples=s - flux, sigma_G=bf / domain.volume, rve_stress=rve_stress,
        rve_contacts=count, rve_mass=rve_mass, xi=xi, couple_flux=flux, body_couple=body,
        spin_inertia=spin, volume=domain.volume)


def _inertia_terms(domain, owner, mass, accel, gravity, xi, n):
    """Body couple 1/V sum_R M_R g_k xi_m and spin inertia 1/V sum_R M_R a'_k xi_m (eq. 12)."""
    zero = np.zeros((3, 3))
    if mass is None:
        if accel is not None or np.any(np.asarray(gravity) != 0):
            raise ValueError("mass (n,) is needed when gravity or accel is given")
        return zero, zero, np.zeros(domain.n_rve)
    mass = _as("mass", mass, (n,))
    g = _as("gravity", gravity, (3,))
    inside = owner >= 0
    rve_mass = np.bincount(owner[inside], mass[inside], minlength=domain.n_rve)
    body = np.einsum("r,k,rm->mk", rve_mass, g, xi) / domain.volume
    if accel is None:
        return body, zero, rve_mass
    accel = _as("accel", accel, (n, 3))
    mom = np.zeros((domain.n_rve, 3))
    np.add.at(mom, owner[inside], mass[inside, None] * accel[inside])
    a_dom = mom.sum(axis=0) / rve_mass.sum()
    rel = mom - rve_mass[:, None] * a_dom  # M_R (a_R - a_domain)
    return body, np.einsum("rk,rm->mk", rel, xi) / domain.volume, rve_mass


class StressRecorder:
    """Records the measures of `micromorphic_stress` every ``every`` steps; writes
    ``name.csv``, ``name.json`` (rows plus the full tensors) and ``name.png`` (mean and
    octahedral shear stress against time, as seed 002 Fig. 5-6) into ``out_dir``.

    ``domain`` is an `AveragingDomain` (fixed) or a callable ``(x, radius) -> domain``
    (e.g. ``lambda x, r: AveragingDomain.around(x[ids], r[ids], (4, 4, 3))`` for a domain
    moving with particles ``ids``). Without ``accel``, accelerations come from the
    velocities of the previous recorded call, (v - v_prev) / (t - t_prev), a secant over
    ``every`` steps; the first record then has no micro-spin inertia. ``options`` go to
    `micromorphic_stress` (gravity, couple_flux, on_empty).
    """

    def __init__(self, domain, out_dir, name: str = "stress", every: int = 1, **options):
        if int(every) < 1:
            raise ValueError(f"every must be an integer >= 1, got {every!r}")
        self.domain, self.every, self.options = domain, int(every), options
        self.out_dir, self.name = Path(out_dir), name
        self.rows: list[dict] = []
        self.tensors: list[dict] = []
        self._prev = None

    def __call__(self, step: int, t: float, x, radius, pairs, force, mass=None, *, v=None,
                 accel=None, xc=None):
        """Record at ``step`` if it is a multiple of ``every``; returns the result or None."""
        if step % self.every:
            return None
        if accel is None and v is not None and self._prev is not None:
            t0, v0 = self._prev
            if v0.shape == np.shape(v) and t > t0:
                accel = (np.asarray(v) - v0) / (t - t0)
        if v is not None:
            self._prev = (float(t), np.array(v, dtype=np.float64))
        dom = self.domain(x, radius) if callable(self.domain) else self.domain
        res = micromorphic_stress(dom, x, radius, pairs, force, mass, accel=accel, xc=xc,
                                  **self.options)
        self.rows.append({"step": int(step), "t": float(t), "has_accel": accel is not None,
                          **res.measures()})
        self.tensors.append({k: getattr(res, k).tolist() for k in
                             ("s", "sigma", "sigma_no_spin", "sigma_no_couples", "sigma_G", "m")}
                            | {"lo": list(dom.lo), "hi": list(dom.hi)})
        return res

    def write(self) -> dict[str, Path]:
        """Write CSV, JSON and PNG; returns their paths."""
        if not self.rows:
            raise ValueError("StressRecorder.write: nothing recorded yet")
        self.out_dir.mkdir(parents=True, exist_ok=True)
        paths = {k: self.out_dir / f"{self.name}.{k}" for k in ("csv", "json", "png")}
        with open(paths["csv"], "w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=list(self.rows[0]))
            w.writeheader()
            w.writerows(self.rows)
        paths["json"].write_text(json.dumps({"rows": self.rows, "tensors": self.tensors}))
        self._plot(paths["png"])
        return paths

    def _plot(self, path):
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        t = [r["t"] for r in self.rows]
        labels = {"s": "s (micro-stress)", "sigma": r"$\sigma$ (Cauchy)",
                  "sigma_no_spin": r"$\sigma$ without $\rho\omega$",
                  "sigma_no_couples": r"$\sigma$ without $\rho\omega$, $\rho\ell$",
                  "sigma_G": r"$\sigma^G$ (granular)"}
        fig, axes = plt.subplots(1, 2, figsize=(11, 4))
        for ax, kind in zip(axes, ("p", "tau"), strict=False):
            for key, lab in labels.items():
                ax.plot(t, [r[f"{kind}_{key}"] for r in self.rows], label=lab)
            sign = -1.0 if kind == "p" else 1.0  # the paper plots -p of the couple stress
            ax.plot(t, [sign * r[f"{kind}_couple_per_xi"] for r in self.rows], "k--",
                    label=("-" if kind == "p" else "") + r"couple / $|\xi|$")
            ax.set_xlabel("t [s]")
            ax.set_ylabel("mean stress p [Pa]" if kind == "p" else "octahedral shear [Pa]")
            ax.grid(alpha=0.3)
        axes[0].legend(fontsize=7)
        fig.tight_layout()
        fig.savefig(path, dpi=110)
        plt.close(fig)


def record_frames(recorder: StressRecorder, paths) -> list:
    """Feed saved contact frames (`dem.io.write_contact_frame`) to a recorder, in order;
    the stress measures on a finished run. Returns the recorder's results."""
    from dem.io import read_contact_frame

    results = []
    for path in paths:
        f = read_contact_frame(path)
        results.append(recorder(f["step"], f["t"], f["x"], f["radius"], f["pairs"], f["force"],
                                f["mass"], v=f["v"]))
    return results
