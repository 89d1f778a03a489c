"""Accelerators of the interface fixed point on linear maps ``H(x) = A x + b`` with a known
solution: IQN-ILS is GMRES on ``(I - A) x = b``, exact after n + 1 updates also where plain
iteration diverges; it beats Aitken and constant relaxation; secant pairs carry over between
steps; the QR2 filter keeps the least-squares problem regular; 2 ranks == serial."""

import dolfinx_solver  # noqa: F401
from mpi4py import MPI

import numpy as np
import pytest

from coupling.interface import IQNILS, Aitken, ConstantRelaxation, DistributedVectors, IQNOptions

N = 12
# non-normal maps (random eigenvectors) with eigenvalues of both signs; "divergent" has
# |lambda| up to 4, where x <- H(x) diverges, but not lambda = 1 (I - A is regular)
SPECTRA = {"contraction": np.linspace(-0.95, 0.9, N),
           "divergent": np.concatenate([np.linspace(-4.0, 0.5, N - 2), [1.5, 3.0]])}
EXACT = 1e-10   # GMRES in n steps, to round-off amplified by the eigenvector basis' condition


def linear_map(spectrum, seed=0):
    rng = np.random.default_rng(seed)
    S = rng.normal(size=(N, N))
    A = S @ np.diag(spectrum) @ np.linalg.inv(S)
    b = rng.normal(size=N)
    return A, b, np.linalg.solve(np.eye(N) - A, b)


def rows(comm) -> np.ndarray:
    """This rank's rows of the length-N vector."""
    return np.array_split(np.arange(N), comm.size)[comm.rank]


def iterate(acc, A, b, comm=MPI.COMM_SELF, tol=1e-10, max_iterations=400, x0=None):
    """Evaluations of H until ``|H(x) - x| < tol |H(x)|``: (count or None, this rank's x)."""
    mine = rows(comm)
    x = np.zeros(len(mine)) if x0 is None else x0[mine].copy()
    for it in range(1, max_iterations + 1):
        full = np.concatenate(comm.allgather(x))
        new, res = acc.update(x, (A @ full + b)[mine])
        if res < tol:
            return it, x
        if not comm.allreduce(np.abs(new).max(initial=0.0), MPI.MAX) < 1e8:   # diverged
            return None, x
        x = new
    return None, x


def serial():
    return DistributedVectors(MPI.COMM_SELF)


@pytest.mark.parametrize("kind", SPECTRA)
def test_iqn_ils_is_exact_after_n_plus_one_updates(kind):
    A, b, x_exact = linear_map(SPECTRA[kind])
    acc = IQNILS(serial(), omega=0.5, options=IQNOptions(filter_limit=0.0))
    x, errors = np.zeros(N), []
    for _ in range(N + 1):
        x, _ = acc.update(x, A @ x + b)
        errors.append(np.abs(x - x_exact).max() / np.abs(x_exact).max())
    assert errors[-1] < EXACT, errors
    assert errors[-2] > 1e3 * EXACT, errors   # n updates are not enough: the count is sharp
    its, x = iterate(IQNILS(serial(), 0.5, IQNOptions(filter_limit=0.0)), A, b)
    assert its == N + 2   # the (n + 2)-th evaluation confirms the solution
    assert np.abs(x - x_exact).max() < EXACT * np.abs(x_exact).max()


@pytest.mark.parametrize("kind", SPECTRA)
def test_iqn_ils_beats_aitken_and_constant_relaxation(kind):
    A, b, x_exact = linear_map(SPECTRA[kind])
    counts = {name: iterate(acc, A, b)[0] for name, acc in
              (("iqn-ils", IQNILS(serial(), 0.5)), ("aitken", Aitken(serial(), 0.5)),
               ("constant", ConstantRelaxation(serial(), 1.0)))}
    print(kind, counts)   # contraction: 14 / 211 / 396, divergent: 14 / None / None
    assert counts["iqn-ils"] <= N + 2
    if kind == "divergent":
        assert counts["aitken"] is None and counts["constant"] is None
    else:
        assert counts["aitken"] > 3 * (N + 2) and counts["constant"] > counts["aitken"]


def test_secant_pairs_carry_over_between_steps():
    """Three steps of the same A with new right-hand sides (loads): the pairs are differences
    of H, so they stay exact for a linear map. Reused over 2 steps, a step takes 2
    evaluations; ``reuse`` counts steps, not pairs: step 2 leaves one pair only, so with
    ``reuse = 1`` step 3 has to learn again."""
    A, _, _ = linear_map(SPECTRA["divergent"])
    loads = np.random.default_rng(5).normal(size=(3, N))
    counts = {}
    for reuse in (0, 1, 2):
        acc, x, counts[reuse] = IQNILS(serial(), 0.5, IQNOptions(reuse=reuse)), np.zeros(N), []
        for b in loads:
            acc.new_step()
            its, x = iterate(acc, A, b, x0=x)
            counts[reuse].append(its)
            assert np.abs(x - np.linalg.solve(np.eye(N) - A, b)).max() < 1e-8 * np.abs(x).max()
    assert counts[0] == [N + 2] * 3, counts
    assert counts[1][:2] == [N + 2, 2] and counts[1][2] > 2, counts
    assert counts[2] == [N + 2, 2, 2], counts


def test_state_dict_continues_exactly():
    """A restart between steps that loads the kept pairs gives the same iterates, bit for
    bit, as the run that never stopped."""
    A, _, _ = linear_map(SPECTRA["divergent"])
    loads = np.random.default_rng(7).normal(size=(3, N))

    def steps(acc, bs, x):
        out = []
        for b in bs:
            acc.new_step()
            for _ in range(4):
                x, _ = acc.update(x, A @ x + b)
                out.append(x.copy())
        return out, x

    options = IQNOptions(reuse=2)
    through, _ = steps(IQNILS(serial(), 0.5, options), loads, np.zeros(N))
    first = IQNILS(serial(), 0.5, options)
    before, x = steps(first, loads[:1], np.zeros(N))
    saved = {k: np.array(v) for k, v in first.state_dict().items()}
    second = IQNILS(serial(), 0.5, options)
    second.load_state(saved)
    after, _ = steps(second, loads[1:], x)
    assert all(np.array_equal(a, b) for a, b in zip(through, before + after, strict=True))
    with pytest.raises(ValueError, match="pair_step"):
        second.load_state({k: v for k, v in saved.items() if k != "pair_step"})


def test_filter_keeps_the_least_squares_problem_regular():
    """Iterating past convergence of a 4-dimensional map adds pairs that the first 4 span:
    the QR2 filter drops them, the iterate stays the solution, nothing turns NaN."""
    n = 4
    rng = np.random.default_rng(2)
    A = rng.normal(size=(n, n)) * 0.6
    b = rng.normal(size=n)
    x_exact = np.linalg.solve(np.eye(n) - A, b)
    acc, x = IQNILS(serial(), 1.0, IQNOptions(filter_limit=1e-2)), np.zeros(n)
    for _ in range(15):
        x, _ = acc.update(x, A @ x + b)
        assert np.all(np.isfinite(x)) and acc.columns <= n
    assert acc.filtered > 0
    assert np.abs(x - x_exact).max() < 1e-10 * np.abs(x_exact).max()


def test_max_columns_keeps_the_newest_pairs():
    A, b, x_exact = linear_map(SPECTRA["contraction"])
    acc = IQNILS(serial(), 0.5, IQNOptions(max_columns=4))
    its, x = iterate(acc, A, b)
    assert its is not None and acc.columns <= 4
    assert np.abs(x - x_exact).max() < 1e-8 * np.abs(x_exact).max()


def test_first_update_and_new_step_relax():
    """Without pairs every accelerator relaxes: ``x + omega (H(x) - x)``; a new step (reuse
    0) forgets the pairs, Aitken's new step its factor."""
    x, t = np.array([1.0, 2.0]), np.array([3.0, -1.0])
    for acc in (IQNILS(serial(), 0.4), Aitken(serial(), 0.4), ConstantRelaxation(serial(), 0.4)):
        new, res = acc.update(x, t)
        assert np.allclose(new, x + 0.4 * (t - x)) and np.isclose(res, np.linalg.norm(t - x) / np.linalg.norm(t))
        acc.update(new, 0.5 * t)
        acc.new_step()
        assert np.allclose(acc.update(x, t)[0], x + 0.4 * (t - x))


def test_bad_options_are_named():
    for kwargs, name in (({"reuse": -1}, "reuse"), ({"max_columns": 0}, "max_columns"),
                         ({"filter_limit": 1.0}, "filter_limit")):
        with pytest.raises(ValueError, match=name):
            IQNOptions(**kwargs)
    with pytest.raises(ValueError, match="omega"):
        IQNILS(serial(), omega=0.0)


@pytest.mark.mpi
@pytest.mark.parametrize("kind", SPECTRA)
def test_iqn_ils_distributed_equals_serial(kind):
    """The vector split over the ranks of COMM_WORLD gives the serial iterates to round-off,
    and every rank solves its least-squares problem with the same coefficients."""
    comm = MPI.COMM_WORLD
    A, b, _ = linear_map(SPECTRA[kind])
    ours, theirs = IQNILS(DistributedVectors(comm), 0.5), IQNILS(serial(), 0.5)
    x, y = np.zeros(len(rows(comm))), np.zeros(N)
    for _ in range(N + 2):
        full = np.concatenate(comm.allgather(x))
        assert np.abs(full - y).max() < 1e-10 * max(np.abs(y).max(), 1.0)
        x, res_x = ours.update(x, (A @ full + b)[rows(comm)])
        y, res_y = theirs.update(y, A @ y + b)
        assert abs(res_x - res_y) < 1e-10   # relative residuals: down to round-off at the end
        coefficients = comm.allgather(ours.coefficients)
        assert all(np.array_equal(c, coefficients[0]) for c in coefficients)
    assert iterate(IQNILS(DistributedVectors(comm), 0.5), A, b, comm)[0] == iterate(
        IQNILS(serial(), 0.5), A, b)[0]


@pytest.mark.mpi
def test_batched_inner_products_equal_single_ones():
    comm = MPI.COMM_WORLD
    space = DistributedVectors(comm)
    rng = np.random.default_rng(comm.rank)
    Q, w = rng.normal(size=(5, 7)), rng.normal(size=7)
    assert np.allclose(space.dots(Q, w), [space.dot(q, w) for q in Q], rtol=1e-14)
    assert space.dots(np.zeros((0, 7)), w).shape == (0,)


def test_state_dict_of_a_rank_without_interface_entries():
    """Under MPI a rank may own none of the prescribed dofs: its pairs are empty rows."""
    acc = IQNILS(DistributedVectors(MPI.COMM_SELF), 0.5)
    for _ in range(3):
        acc.update(np.zeros(0), np.zeros(0))
    saved = acc.state_dict()
    assert saved["dr"].shape == (len(saved["pair_step"]), 0)
    again = IQNILS(DistributedVectors(MPI.COMM_SELF), 0.5)
    again.load_state(saved)
    assert again.state_dict()["dr"].shape == saved["dr"].shape
