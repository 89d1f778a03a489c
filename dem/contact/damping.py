"""Normal dashpot on the velocity at the end of the step (the damping sub-model of both laws).

Velocity Verlet evaluates the forces of step n+1 at the half-step velocity v(n+1/2); a
dashpot on it lags half a step, which is first order in dt (restitution at e = 0.1 was
10-14 % low at the default step, tests/dem/test_restitution.py). The dashpot here acts on a
prediction of the normal approach speed at the end of the step instead,

    vn(n+1) ~ vn + h [q - fn/m*],      h = dt/2,

where -fn/m* is the pair's own normal force (taken implicitly: fn is the force being
computed) and q the relative normal acceleration from everything else (the grains' other
contacts, gravity, a wall's or a prescribed grain's motion), taken from the last step: the
change of vn between the last two force passes is dt times the relative acceleration then,
own force fn_old included, so q dt = vn - vn_old + dt fn_old / m*. Solving
fn = F_el + gamma vn(n+1) for fn:

    fn = (F_el + gamma (vn + (vn - vn_old)/2 + h fn_old / m*)) / (1 + gamma h / m*).

At the first pass in contact (fn_old = 0: no history) the others' acceleration is unknown
and taken as zero (the pair-local implicit dashpot). It is exactly the elastic force at rest
(vn = vn_old = 0, fn_old = F_el is its fixed point), so a grain carrying a load has no
dashpot force and a sheared packing's dashpots do no positive work.

The touch and the release fall inside a step: a dashpot force that jumps in (linear law) or
rises steeply (Hertz, gamma ~ delta^(1/4)) at the touch is sampled once a step, which made one
collision's e depend on the touch instant within the step by up to 12 % of e at e = 0.1.
At the first pass in contact, touched tau = delta / vn ago (exactly, for the drift's
straight motion), and at a pass after which the contact is predicted to open (tau = delta /
the separation speed of the next drift ahead), the dashpot coefficient is weighted by the
impulse of a force growing from the touch (falling to the release) like tau^p (p = 0 linear,
1/4 Hertz) over the pass's interval and the neighbouring pass's that sees no contact
(`_partial_step`); a release pass that took part of the next pass's interval and was wrong
(the contact still closed at the next pass) leaves that part as the history's claim, which
the next pass leaves out. Restitution of a binary collision or a wall impact at the default
step: the mean over touch instants within 0.2 % of the contact ODE, each instant within
0.8 % (tests/dem/test_restitution.py; 14 % and 12 % before).

The history (`dem.contact.HIST`) keeps fn_old, vn_old and the claim per contact; q comes
from the contact's own history only, so the force needs nothing from the particles beyond
the pair (the same bits on any MPI decomposition). m* is the pair's reduced mass, also for a
GHOST or FIXED partner: the error is then dt/2 times the change of fn over the step, second
order, and a pair of two prescribed grains moving rigidly (vn = vn_old = 0) keeps fn = F_el.

h = 0 gives the plain dashpot F_el + gamma vn: for a force pass at full-step velocities (the
constructor's, `Simulation.compute_forces`, `Simulation.contact_forces`).
"""

from __future__ import annotations

from numba import njit

__all__ = ["normal_dashpot"]


@njit(cache=True, inline="always")
def _partial_step(x, c, p):
    """Weight of the dashpot force at the force pass next to a touch or a release that lies
    x dt (0 < x <= 1) away from the pass, for a dashpot force growing from the touch (or
    falling to the release) like its distance in time to the power p: the impulse of the
    force from the touch (to the release) over the pass's half-steps and the other pass's
    (which sees no contact), but for the first c dt of the pass's interval (claimed by the
    last pass already), in units of dt times the force at the pass:
    (x + 1/2 - c)^(1 + p) / ((1 + p) x^p)."""
    if p == 0.0:
        return x + 0.5 - c
    return (x + 0.5 - c) ** (1.0 + p) / ((1.0 + p) * x**p)


@njit(cache=True, inline="always")
def normal_dashpot(fel, gam, vn, meff, fo, vo, co, h, delta, p):
    """Normal force [N] of elastic force fel [N] and dashpot coefficient gam [N s/m] at
    normal approach speed vn [m/s] (the half-step velocity), reduced mass meff [kg], the
    contact's normal force fo [N], vn vo [m/s] and claim co at the last force pass (fo = 0:
    none), predicting half a step h [s] ahead (h = 0: the plain dashpot fel + gam vn);
    overlap delta [m], the dashpot force growing like delta^p near delta = 0 (the law's
    exponent: 0 linear, 1/4 Hertz). Returns (fn, claim): the part of the next pass's
    interval, in steps, whose dashpot impulse this pass took (a release predicted after
    the middle of the next step). Scalars only (see
    `dem.contact.kinematics.contact_kinematics`)."""
    if h == 0.0 or gam == 0.0:  # (gam = 0: fel to the bit, no dashpot in the ledger)
        return fel + gam * vn, 0.0
    dt = 2.0 * h
    if fo == 0.0:  # the first pass in contact: touched delta / vn ago
        if vn > 0.0 and delta < dt * vn:
            gam *= _partial_step(delta / (dt * vn), 0.0, p)
        return (fel + gam * vn) * meff / (meff + gam * h), 0.0
    u = vn + 0.5 * (vn - vo)  # the speed at the pass but for the change of the own force
    g = gam * (1.0 - co)
    fn = ((fel + g * u) * meff + g * h * fo) / (meff + g * h)
    # m* times the separation speed over the next drift, vn - 2 vp, vp = u + h (fo - fn)/m*
    sm = (vn - 2.0 * u) * meff - dt * (fo - fn)
    if sm > 0.0 and delta * meff < sm * dt:  # the contact opens before the next pass
        x = delta * meff / (sm * dt)
        g = gam * _partial_step(x, co, p)
        fn = ((fel + g * u) * meff + g * h * fo) / (meff + g * h)
        return fn, max(x - 0.5, 0.0)
    return fn, 0.0
