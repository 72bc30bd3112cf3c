"""Local Explicit against an integrated QP built from the problem's definition alone.

``solve_reference`` condenses the integrated MPC with the project's own code
(``problem.condensed_qp`` from ``prediction``). Here the integrated MPC is
built again from the problem's definition alone (eq_linear simulated in numpy,
the cost summed as printed) on problems with what the generated ones lack: a
per-step disturbance and reference, two outputs with a non-diagonal Q (or a
singular one), an agent with two inputs and a non-diagonal R, a shared agent
and an active general row with a per-step right-hand side.

The default run checks each KKT path (dense, Woodbury factored, Riccati) on
one problem each, both objective counts and a singular Q; ``-m slow`` adds the
other pairings of path, objective count and Q (the same check, more compiles).
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ampc_jax.formulations import LocalExplicit
from ampc_jax.problem import Agent, CondensedQP, Constraint, Objective, Problem, condensed_qp
from ampc_jax.reference import clarabel_solve
from ampc_jax.results import Status

pytestmark = pytest.mark.timeout(300)

TIGHT_TOL = dict(tol_primal=1e-14, tol_dual=1e-14)
ATOL = 1e-6  # absolute floor of the "1e-3 relative" comparison (inputs near zero)


def stack(datas):
    return jax.tree.map(lambda *x: jnp.stack(x), *datas)


def rich_spec(seed, n_obj, singular_q=False, horizon=6):
    """Objective o0: outputs (2) of subsystem 0, inputs from agent a0 (2 inputs)
    and the shared agent s01; o_j (j >= 1): one output of subsystem j, private
    agent p_j, shared s_(j-1)j and s_j(j+1). General row a0_0 + a0_1 / 2 - s01 <= b^(k)."""
    rng = np.random.default_rng(seed)
    ns, N = 2, horizon
    nx = ns * n_obj
    A = np.zeros((nx, nx))
    for j in range(n_obj):
        M = rng.standard_normal((ns, ns))
        M = 0.9 * M / max(1.0, np.max(np.abs(np.linalg.eigvals(M))))
        A[j * ns : (j + 1) * ns, j * ns : (j + 1) * ns] = 0.5 * np.eye(ns) + 0.5 * M

    def agent(name, subsystems, R):
        B = np.zeros((nx, len(R)))
        for j in subsystems:
            B[j * ns : (j + 1) * ns] = rng.standard_normal((ns, len(R)))
        lb, ub = -rng.uniform(0.5, 1.0, len(R)), rng.uniform(0.5, 1.0, len(R))
        return dict(name=name, B=B, R=np.asarray(R, float), lb=lb, ub=ub)

    agents = [agent("a0", [0], [[0.5, 0.4], [0.4, 0.4]])]
    agents += [agent(f"p{j}", [j], [[rng.uniform(0.02, 0.2)]]) for j in range(1, n_obj)]
    agents += [
        agent(f"s{j}{j + 1}", [j, j + 1], [[rng.uniform(0.02, 0.2)]]) for j in range(n_obj - 1)
    ]
    k = np.arange(1, N + 1)[:, None]  # the reference of C_j X^(k), k = 1..N_p
    C0 = np.zeros((2, nx))
    C0[:, :ns] = [[1.0, 0.0], [0.4, 1.0]]
    Q0 = [[1.0, 1.0], [1.0, 1.0]] if singular_q else [[4.0, 1.5], [1.5, 2.0]]
    ref0 = 2.0 * rng.uniform(-1, 1, 2) + np.sin(0.7 * k + rng.uniform(0, 6, 2))
    objectives = [dict(name="o0", C=C0, Q=np.asarray(Q0), ref=ref0)]
    for j in range(1, n_obj):
        C = np.zeros((1, nx))
        C[0, j * ns] = 1.0
        Q = np.array([[rng.uniform(1, 10) * 10.0**j]])  # unequal rho_j
        ref = 2.0 * rng.uniform(-1, 1) + np.cos(0.5 * k + rng.uniform(0, 6))
        objectives.append(dict(name=f"o{j}", C=C, Q=Q, ref=ref))
    w = 0.3 * rng.standard_normal((N, nx))
    x0 = rng.standard_normal(nx)
    rows = {"a0": np.array([[1.0, 0.5]]), "s01": np.array([[-1.0]])}
    b = (-0.3 + 0.1 * rng.uniform(-1, 1, N))[:, None]
    return dict(horizon=N, A=A, x0=x0, w=w, agents=agents, objectives=objectives, rows=rows, b=b)


def problem_of(spec):
    return Problem(
        horizon=spec["horizon"],
        A=spec["A"],
        x0=spec["x0"],
        w=spec["w"],
        agents=[Agent(a["name"], a["B"], a["R"], a["lb"], a["ub"]) for a in spec["agents"]],
        objectives=[Objective(o["name"], o["C"], o["Q"], o["ref"]) for o in spec["objectives"]],
        constraints=[Constraint(spec["rows"], spec["b"])],
    )


def independent_qp(spec):
    """min 1/2 U'HU + q'U s.t. G U <= h, U = [U^(0); ...; U^(N_p-1)], from the
    definition only: the map U -> X^(1..N_p) by simulating X^(k+1) = A X^(k) +
    sum_i B_(i) U_(i)^(k) + w^(k) for unit inputs; the cost sum_j sum_{k=1..N_p}
    ||C_j X^(k) - ref_j^(k)||^2_Q_j + sum_i sum_{k=0..N_p-1} ||U_(i)^(k)||^2_R_(i);
    per step the rows U <= ub, -U <= -lb and the general row. Returns H, q, G, h
    and the indices of the general row in G (one per step)."""
    N, A = spec["horizon"], spec["A"]
    nx = A.shape[0]
    agents = spec["agents"]
    sizes = [a["B"].shape[1] for a in agents]
    off = np.cumsum([0, *sizes])
    nu = off[-1]
    Bf = np.hstack([a["B"] for a in agents])

    def simulate(U, x, w):
        xs = []
        for k in range(N):
            x = A @ x + Bf @ U[k] + w[k]
            xs.append(x)
        return np.concatenate(xs)  # X^(1..N_p)

    free = simulate(np.zeros((N, nu)), spec["x0"], spec["w"])
    zero_x, zero_w = np.zeros(nx), np.zeros((N, nx))
    Phi = np.stack([simulate(e.reshape(N, nu), zero_x, zero_w) for e in np.eye(N * nu)], 1)
    Rstep = np.zeros((nu, nu))
    for i, a in enumerate(agents):
        Rstep[off[i] : off[i + 1], off[i] : off[i + 1]] = a["R"]
    H = 2.0 * np.kron(np.eye(N), Rstep)
    q = np.zeros(N * nu)
    for o in spec["objectives"]:
        Cb, Qb = np.kron(np.eye(N), o["C"]), np.kron(np.eye(N), o["Q"])
        Y = Cb @ Phi
        e0 = Cb @ free - np.asarray(o["ref"]).reshape(-1)
        H += 2.0 * Y.T @ Qb @ Y
        q += 2.0 * Y.T @ Qb @ e0
    lb = np.concatenate([a["lb"] for a in agents])
    ub = np.concatenate([a["ub"] for a in agents])
    names = [a["name"] for a in agents]
    G, h, general = [], [], []
    for k in range(N):
        for m in range(nu):
            e = np.zeros(N * nu)
            e[k * nu + m] = 1.0
            G += [e, -e]
            h += [ub[m], -lb[m]]
        row = np.zeros(N * nu)
        for name, coeff in spec["rows"].items():
            i = names.index(name)
            row[k * nu + off[i] : k * nu + off[i + 1]] = np.asarray(coeff)[0]
        general.append(len(G))
        G.append(row)
        h.append(spec["b"][k, 0])
    return H, q, np.array(G), np.array(h), np.array(general)


def clarabel_qp(H, q, G, h):
    sol = clarabel_solve(CondensedQP(H=H, E=q, G=G, h=h), eps=1e-11)
    assert str(sol.status) in ("Solved", "AlmostSolved"), sol.status  # 1e-11: see clarabel()
    return np.asarray(sol.x), np.asarray(sol.z), np.asarray(sol.s)


def perturbed(spec, what):
    """The definition with one feature dropped: the comparison must then fail."""
    s = dict(spec, agents=[dict(a) for a in spec["agents"]])
    s["objectives"] = [dict(o) for o in spec["objectives"]]
    o0, a0 = s["objectives"][0], s["agents"][0]
    if what == "no disturbance":
        s["w"] = np.zeros_like(spec["w"])
    elif what == "disturbance held":
        s["w"] = np.broadcast_to(spec["w"][0], spec["w"].shape)
    elif what == "reference held":
        for o in s["objectives"]:
            o["ref"] = np.broadcast_to(o["ref"][0], o["ref"].shape)
    elif what == "reference one step early":  # ref_j^(k+1) applied to X^(k)
        for o in s["objectives"]:
            o["ref"] = np.concatenate([o["ref"][1:], o["ref"][-1:]])
    elif what == "Q diagonal":
        o0["Q"] = np.diag(np.diag(o0["Q"]))
    elif what == "R diagonal":
        a0["R"] = np.diag(np.diag(a0["R"]))
    elif what == "no general row":
        s["b"] = np.full_like(spec["b"], 1e3)
    return s


PERTURBATIONS = (
    "no disturbance",
    "disturbance held",
    "reference held",
    "reference one step early",
    "Q diagonal",
    "R diagonal",
    "no general row",
)


@pytest.mark.timeout(120)
@pytest.mark.parametrize(
    "n_obj,singular_q,path",
    [
        pytest.param(2, False, "dense", marks=pytest.mark.slow),
        (2, False, "woodbury_factored"),
        (3, False, "dense"),
        pytest.param(3, False, "woodbury", marks=pytest.mark.slow),
        (2, True, "dense"),
        pytest.param(2, True, "woodbury_factored", marks=pytest.mark.slow),
        pytest.param(2, False, "riccati", marks=pytest.mark.slow),
        (3, True, "riccati"),
    ],
)
def test_matches_independent_integrated_qp(n_obj, singular_q, path):
    specs = [rich_spec(seed, n_obj, singular_q) for seed in (1, 2, 3, 4)]
    problems = [problem_of(s) for s in specs]
    T = problems[0].topology
    assert all(p.topology == T for p in problems)
    assert max(T.multiplicity) >= 2 and T.output_sizes[0] == 2 and T.agent_sizes[0] == 2
    assert len(T.general_agents) == 1
    if singular_q:
        assert abs(np.linalg.eigvalsh(specs[0]["objectives"][0]["Q"])[0]) < 1e-12
    solver = LocalExplicit(T, max_iter=30000, kkt=path)
    assert solver.kkt_solve.name == path
    datas = [p.data() for p in problems]
    q = solver.params(**TIGHT_TOL)
    res = jax.jit(jax.vmap(solver.solve, in_axes=(0, None)))(stack(datas), q)
    assert np.all(np.asarray(res.status) == Status.SOLVED), np.asarray(res.iterations)
    u0 = np.asarray(res.u0)
    nu = T.n_u

    def error(u, ref):  # <= 1: within 1e-3 relative per input, 1e-6 absolute floor
        return np.max(np.abs(u - ref) / (1e-3 * np.abs(ref) + ATOL))

    missed = {what: 0.0 for what in PERTURBATIONS}
    active_first = 0
    for b, spec in enumerate(specs):
        H, q, G, h, general = independent_qp(spec)
        # the solver's own condensing (the reference of the other tests) agrees
        qp = condensed_qp(T, datas[b])
        np.testing.assert_allclose(qp.H, H, rtol=1e-10, atol=1e-10 * np.abs(H).max())
        np.testing.assert_allclose(qp.E, q, rtol=1e-10, atol=1e-10 * np.abs(q).max())
        x, z, s = clarabel_qp(H, q, G, h)
        assert error(u0[b], x[:nu]) <= 1.0, (b, u0[b], x[:nu])
        # the general row is active (zero slack, positive multiplier) at some step
        active = (s[general] < 1e-7) & (z[general] > 1e-6)
        assert active.any(), (b, s[general], z[general])
        active_first += int(active[0])
        for what in PERTURBATIONS:
            xp = clarabel_qp(*independent_qp(perturbed(spec, what))[:4])[0]
            missed[what] = max(missed[what], error(u0[b], xp[:nu]))
    assert active_first > 0  # and binds the compared first-step inputs somewhere
    # every feature matters: without it the comparison above fails
    assert not [w for w, e in missed.items() if e <= 3.0], missed
