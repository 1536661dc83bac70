"""Does treating talos's joint damping implicitly pay? Evaluations to reach an accuracy, against dp54.

Issue 15's talos target at 1e-6 is missed because the URDF damps light joints (eigenvalues of M⁻¹D up to ~900 /s):
dp54 sits at its stability limit (steps of ~3 ms) whatever the tolerance, and without the damping it needs about a
quarter of the evaluations. This study prototypes, in Python, three methods that take the damping term linearly
implicitly, with J ≈ [[0, I], [0, −M₀⁻¹D]] and M₀ = CRBA at the step's start (one factorization of M₀ + hγD per
step; the configuration advances on the chart at the step's start, as the package's integrators do):

- ROS34PW2 (Rang & Angermann 2005): a Rosenbrock-W method of order 3(2), L-stable, 4 evaluations a step; W-methods
  keep their order with any Jacobian approximation.
- ARK4(3)6L[2]SA and ARK5(4)8L[2]SA (Kennedy & Carpenter 2003/2019, SUNDIALS' ARKODE tables): additive IMEX
  Runge–Kutta pairs, explicit on a − f_I, ESDIRK (L-stable, stiffly accurate) on f_I = −M₀⁻¹D v, which is linear:
  each implicit stage is one solve with M₀ + hγD. 6 and 8 evaluations a step.

Each runs under the package's PI controller (`step_control.PIController`) with the package's error norm, and so
does a dp54 in the same loop (the package's tableau), so all are counted alike; the error is `work_precision`'s
(max over samples of the tangent-space state error against dop853 at rtol = atol = 1e-14), on samples every
0.25 s, which the runs land on (work_precision's 20 ms samples would force steps on runs whose steps are longer).
Before that, each method's order is checked on a damped pendulum with fixed steps (against SciPy's DOP853 at
1e-13). The cost estimate adds, per step, one CRBA and one Cholesky factorization (timed through Pinocchio's Python
bindings: an upper bound) to the evaluations at the native dp54's measured CPU time per evaluation.

Prints, per system and method, each tolerance's error, evaluations, steps and estimated native CPU time, then the
cheapest run of each method reaching 1e-6 and 1e-8. About 2 minutes on 2 cores.

Usage: .venv/bin/python scripts/damping_imex_study.py [--tolerances 1e-5,3.16e-6,...] [--duration 1]
"""

from __future__ import annotations

import argparse
import math
import sys
import time
import timeit
from collections.abc import Callable
from fractions import Fraction
from pathlib import Path

import numpy as np
import pinocchio as pin
from scipy.integrate import solve_ivp

import multibody_sim as ms
from multibody_sim.integrators.tableau import DORMAND_PRINCE_54
from multibody_sim.state import chart_terms
from multibody_sim.step_control import PIController

sys.path.insert(0, str(Path(__file__).resolve().parent))
from work_precision_report import SYSTEMS, initial_state  # noqa: E402  (the report's talos state)

SAMPLE = 0.25  # [s] error samples: few, so that landing on them costs the adaptive runs next to nothing
TOLERANCES = (1e-5, 3.16e-6, 1e-6, 3.16e-7, 1e-7, 3.16e-8, 1e-8, 3.16e-9, 1e-9)
ACCURACIES = (1e-6, 1e-8)


def frac(text: str) -> list[Fraction]:
    """Fractions from 'n/d n/d ...' (0 for an absent entry)."""
    return [Fraction(x) for x in text.split()]


# ---- ROS34PW2 (Rang & Angermann 2005, BIT 45: 761-787), non-transformed form ------------------------------------
ROS_GAMMA = 4.3586652150845900e-01
ROS_ALPHA = np.array([[0, 0, 0, 0], [8.7173304301691801e-01, 0, 0, 0],
                      [8.4457060015369423e-01, -1.1299064236484185e-01, 0, 0], [0, 0, 1, 0]])  # fmt: skip
ROS_G = np.array([[0, 0, 0, 0], [-8.7173304301691801e-01, 0, 0, 0],
                  [-9.0338057013044082e-01, 5.4180672388095326e-02, 0, 0],
                  [2.4212380706095346e-01, -1.2232505839045147e00, 5.4526025533510214e-01, 0]])  # fmt: skip
ROS_B = np.array([2.4212380706095346e-01, -1.2232505839045147e00, 1.5452602553351020e00, 4.3586652150845900e-01])
ROS_BHAT = np.array([3.7810903145819369e-01, -9.6042292212423178e-02, 5.0e-01, 2.1793326075422950e-01])

# ---- ARK4(3)6L[2]SA (Kennedy & Carpenter 2003, Appl. Numer. Math. 44: 139-181) -----------------------------------
ARK4_E = [frac("0"), frac("1/2"), frac("13861/62500 6889/62500"),
          frac("-116923316275/2393684061468 -2731218467317/15368042101831 9408046702089/11113171139209"),
          frac("-451086348788/2902428689909 -2682348792572/7519795681897 12662868775082/11960479115383 "
               "3355817975965/11060851509271"),
          frac("647845179188/3216320057751 73281519250/8382639484533 552539513391/3454668386233 "
               "3354512671639/8306763924573 4040/17871")]  # fmt: skip
ARK4_I = [frac("0"), frac("1/4"), frac("8611/62500 -1743/31250"),
          frac("5012029/34652500 -654441/2922500 174375/388108"),
          frac("15267082809/155376265600 -71443401/120774400 730878875/902184768 2285395/8070912"),
          frac("82889/524892 0 15625/83664 69875/102672 -2260/8211")]  # fmt: skip
ARK4_B = frac("82889/524892 0 15625/83664 69875/102672 -2260/8211 1/4")
ARK4_BHAT = frac("4586570599/29645900160 0 178811875/945068544 814220225/1159782912 -3700637/11593932 61727/225920")
# ---- ARK5(4)8L[2]SA (Kennedy & Carpenter 2003), as SUNDIALS' ARK548L2SA_ERK_8_4_5 / _DIRK_8_4_5 --------------------
ARK5_E = [frac("0"), frac("41/100"), frac("367902744464/2072280473677 677623207551/8224143866563"),
          frac("1268023523408/10340822734521 0 1029933939417/13636558850479"),
          frac("14463281900351/6315353703477 0 66114435211212/5879490589093 -54053170152839/4284798021562"),
          frac("14090043504691/34967701212078 0 15191511035443/11219624916014 -18461159152457/12425892160975 "
               "-281667163811/9011619295870"),
          frac("19230459214898/13134317526959 0 21275331358303/2942455364971 -38145345988419/4862620318723 -1/8 "
               "-1/8"),
          frac("-19977161125411/11928030595625 0 -40795976796054/6384907823539 177454434618887/12078138498510 "
               "782672205425/8267701900261 -69563011059811/9646580694205 7356628210526/4942186776405")]  # fmt: skip
ARK5_B = frac("-872700587467/9133579230613 0 0 22348218063261/9555858737531 -1143369518992/8141816002931 "
              "-39379526789629/19018526304540 32727382324388/42900044865799 41/200")  # fmt: skip
ARK5_I = [frac("0"), frac("41/200"), frac("41/400 -567603406766/11931857230679"),
          frac("683785636431/9252920307686 0 -110385047103/1367015193373"),
          frac("3016520224154/10081342136671 0 30586259806659/12414158314087 -22760509404356/11113319521817"),
          frac("218866479029/1489978393911 0 638256894668/5436446318841 -1179710474555/5321154724896 "
               "-60928119172/8023461067671"),
          frac("1020004230633/5715676835656 0 25762820946817/25263940353407 -2161375909145/9755907335909 "
               "-211217309593/5846859502534 -4269925059573/7827059040749"),
          ARK5_B[:7]]  # fmt: skip
ARK5_BHAT = frac("-975461918565/9796059967033 0 0 78070527104295/32432590147079 -548382580838/3424219808633 "
                 "-33438840321285/15594753105479 3629800801594/4656183773603 4035322873751/18575991585200")  # fmt: skip


def square(rows: list[list[Fraction]], diagonal: Fraction = Fraction(0)) -> np.ndarray:
    """A lower-triangular (s, s) float matrix from its rows below the diagonal, with `diagonal` on it (row 0: 0)."""
    s = len(rows)
    out = np.zeros((s, s))
    for i, row in enumerate(rows):
        out[i, : len(row)] = [float(x) for x in row]
        if i:
            out[i, i] = float(diagonal)
    return out


class IMEX:
    """An additive pair: explicit table AE, ESDIRK table AI (diagonal gamma), shared weights b, embedded b_hat."""

    def __init__(self, name: str, order: int, AE: list, AI: list, b: list, b_hat: list, gamma: Fraction):
        self.name, self.order = name, order
        self.AE, self.AI, self.gamma = square(AE), square(AI, gamma), float(gamma)
        self.b, self.b_hat = np.array([float(x) for x in b]), np.array([float(x) for x in b_hat])


ARK4 = IMEX("ark436", 4, ARK4_E, ARK4_I, ARK4_B, ARK4_BHAT, Fraction(1, 4))
ARK5 = IMEX("ark548", 5, ARK5_E, ARK5_I, ARK5_B, ARK5_BHAT, Fraction(41, 200))
DP54_A, DP54_B = np.array(DORMAND_PRINCE_54.a), np.array(DORMAND_PRINCE_54.b)
DP54_E = DP54_B - np.array(DORMAND_PRINCE_54.b_hat)


# ---- one step of each method: (q_next, v_next, error vector over (xi, v), evaluations) ---------------------------
class Dynamics:
    """The robot's accelerations with no torque, counted; M(q) and D for the linearly implicit methods."""

    def __init__(self, robot: ms.Robot):
        self.robot, self.D, self.evaluations, self.factorizations = robot, robot.damping.copy(), 0, 0
        self.zero = np.zeros(robot.nv)

    def __call__(self, q: np.ndarray, v: np.ndarray) -> np.ndarray:
        self.evaluations += 1
        return self.robot.unchecked_forward_dynamics(q, v, self.zero)

    def factor(self, q: np.ndarray, hg: float) -> tuple[np.ndarray, Callable[[np.ndarray], np.ndarray]]:
        """M(q) and the solve with M + hg·D (Cholesky)."""
        self.factorizations += 1
        M = self.robot.mass_matrix(q)
        L = np.linalg.cholesky(M + hg * np.diag(self.D))
        return M, lambda r: np.linalg.solve(L.T, np.linalg.solve(L, r))


def ros_step(f: Dynamics, q: np.ndarray, v: np.ndarray, h: float, terms: int):
    """ROS34PW2: (I − hγJ) k_i = h f(y + Σ α_ij k_j) + hJ Σ γ_ij k_j, J = [[0, I], [0, −M⁻¹D]]; y' = y + Σ b_i k_i."""
    space, nv = f.robot.space, len(v)
    M, solve = f.factor(q, h * ROS_GAMMA)
    Kq, Kv = np.zeros((4, nv)), np.zeros((4, nv))
    for i in range(4):
        xi, vs = ROS_ALPHA[i, :i] @ Kq[:i], v + ROS_ALPHA[i, :i] @ Kv[:i]
        rate = vs if i == 0 else space.chart_velocity(xi, vs, terms)
        gv = ROS_G[i, :i] @ Kv[:i]
        rq = h * (rate + gv)  # J's q-row is [0, I]
        rv = h * (f(space.integrate(q, xi), vs) - np.linalg.solve(M, f.D * gv))
        Kv[i] = solve(M @ rv)  # (M + hγD) k_v = M r_v
        Kq[i] = rq + h * ROS_GAMMA * Kv[i]
    e = ROS_B - ROS_BHAT
    return space.integrate(q, ROS_B @ Kq), v + ROS_B @ Kv, np.concatenate((e @ Kq, e @ Kv))


def imex_step(f: Dynamics, q: np.ndarray, v: np.ndarray, h: float, terms: int, method: IMEX):
    """An IMEX ARK step: stage v_i = r_i + hγ f_I(v_i), f_I = −M₀⁻¹D v, i.e. (M₀ + hγD) v_i = M₀ r_i."""
    space, nv, s = f.robot.space, len(v), len(method.b)
    M, solve = f.factor(q, h * method.gamma)
    FEq, FEv, FI = np.zeros((s, nv)), np.zeros((s, nv)), np.zeros((s, nv))
    FI[0] = -np.linalg.solve(M, f.D * v)
    FEq[0], FEv[0] = v, f(q, v) - FI[0]
    for i in range(1, s):
        xi = h * (method.AE[i, :i] @ FEq[:i])
        r = v + h * (method.AE[i, :i] @ FEv[:i] + method.AI[i, :i] @ FI[:i])
        vs = solve(M @ r)
        FI[i] = (vs - r) / (h * method.gamma)
        FEq[i] = space.chart_velocity(xi, vs, terms)
        FEv[i] = f(space.integrate(q, xi), vs) - FI[i]
    e = method.b - method.b_hat
    Fv = FEv + FI
    return (space.integrate(q, h * (method.b @ FEq)), v + h * (method.b @ Fv),
            h * np.concatenate((e @ FEq, e @ Fv)))  # fmt: skip


def dp54_step(f: Dynamics, q: np.ndarray, v: np.ndarray, h: float, terms: int):
    """dp54 on the chart (the package's tableau; no FSAL reuse here: its evaluations are counted as 6 a step)."""
    space, nv = f.robot.space, len(v)
    Kq, Kv = np.zeros((7, nv)), np.zeros((7, nv))
    Kq[0], Kv[0] = v, f(q, v)
    for i in range(1, 7):
        xi, vs = h * (DP54_A[i, :i] @ Kq[:i]), v + h * (DP54_A[i, :i] @ Kv[:i])
        Kq[i], Kv[i] = space.chart_velocity(xi, vs, terms), f(space.integrate(q, xi), vs)
    f.evaluations -= 1  # first same as last: the last stage is the next step's first
    return (space.integrate(q, h * (DP54_B @ Kq)), v + h * (DP54_B @ Kv),
            h * np.concatenate((DP54_E @ Kq, DP54_E @ Kv)))  # fmt: skip


METHODS = {  # name: (step, embedded order for the controller)
    "ros34pw2": (ros_step, 2),
    "ark436": (lambda f, q, v, h, terms: imex_step(f, q, v, h, terms, ARK4), 3),
    "ark548": (lambda f, q, v, h, terms: imex_step(f, q, v, h, terms, ARK5), 4),
    "dp54": (dp54_step, 4),
}


def run(robot: ms.Robot, q0: np.ndarray, v0: np.ndarray, method: str, tol: float, duration: float):
    """Samples every SAMPLE s (landing on each), evaluations, steps and factorizations of one adaptive run."""
    step, embedded = METHODS[method]
    f, space = Dynamics(robot), robot.space
    control = PIController(error_order=embedded, first_step=1e-3)
    terms = chart_terms(5)
    q, v, t, samples, steps = q0.copy(), v0.copy(), 0.0, [], 0
    for k in range(1, round(duration / SAMPLE) + 1):
        stop = k * SAMPLE
        while t < stop:
            t_next = control.propose(stop)
            h = t_next - t
            qn, vn, err = step(f, q, v, h, terms)
            size = np.concatenate((np.maximum(abs(space.difference(space.neutral, q)),
                                              abs(space.difference(space.neutral, qn))),
                                   np.maximum(abs(v), abs(vn))))  # fmt: skip
            norm = math.sqrt(np.mean((err / (tol + tol * size)) ** 2))
            if control.judge(h, norm if math.isfinite(norm) else math.inf):
                control.commit(t_next)
                t, q, v, steps = t_next, qn, vn, steps + 1
        samples.append((q.copy(), v.copy()))
    return samples, f.evaluations, steps, f.factorizations


def check_orders() -> None:
    """Fixed-step orders on a damped pendulum x'' = −sin x − 0.7 x' (through a 1-dof stand-in of the step code)."""

    class Pendulum:
        nv, damping = 1, np.array([0.7])

        class space:  # noqa: N801 (a namespace standing in for ConfigurationSpace on R)
            neutral = np.zeros(1)
            integrate = staticmethod(lambda q, xi: q + xi)
            difference = staticmethod(lambda a, b: b - a)
            chart_velocity = staticmethod(lambda xi, v, terms: v)

        def unchecked_forward_dynamics(self, q, v, tau):
            return -np.sin(q) - self.damping * v

        def mass_matrix(self, q):
            return np.eye(1)

    pendulum, T, y0 = Pendulum(), 2.0, (1.2, 0.3)
    exact = solve_ivp(lambda t, y: [y[1], -math.sin(y[0]) - 0.7 * y[1]], (0, T), y0, rtol=1e-13, atol=1e-13,
                      method="DOP853").y[:, -1]  # fmt: skip
    for name, (step, _) in METHODS.items():
        errors = []
        for n in (20, 40, 80):
            f = Dynamics.__new__(Dynamics)
            f.robot, f.D, f.evaluations, f.factorizations, f.zero = pendulum, pendulum.damping, 0, 0, np.zeros(1)
            q, v = np.array([y0[0]]), np.array([y0[1]])
            for _ in range(n):
                q, v, _ = step(f, q, v, T / n, 5)
            errors.append(max(abs(q[0] - exact[0]), abs(v[0] - exact[1])))
        orders = [math.log2(errors[i] / errors[i + 1]) for i in range(2)]
        print(f"order check {name}: fixed-step errors {', '.join(f'{e:.1e}' for e in errors)}; observed orders "
              f"{orders[0]:.2f}, {orders[1]:.2f}")  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tolerances", default=",".join(f"{x:g}" for x in TOLERANCES))
    parser.add_argument("--duration", type=float, default=1.0)
    args = parser.parse_args(argv)
    check_orders()
    system = SYSTEMS["talos"]
    tolerances = [float(x) for x in args.tolerances.split(",")]
    for damped in (True, False):
        robot = ms.load_robot("talos", floating_base=True, damping=damped)
        q0, v0 = initial_state(robot, system)
        ref = ms.simulate(robot, q0, v0, duration=args.duration, dt=1e-3, integrator="dop853", rtol=1e-14,
                          atol=1e-14, output_dt=SAMPLE)  # fmt: skip
        Q, V = np.asarray(ref.q)[1:], np.asarray(ref.v)[1:]
        per_eval = math.inf
        for _ in range(3):  # the native dp54's CPU time per evaluation, least of 3 runs at a tight tolerance
            start = time.process_time()
            native = ms.simulate(robot, q0, v0, duration=args.duration, dt=1e-3, integrator="dp54", rtol=1e-9,
                                 atol=1e-9, output_dt=SAMPLE)  # fmt: skip
            per_eval = min(per_eval, (time.process_time() - start) / native.stats["evaluations"])
        M = robot.mass_matrix(q0)
        timer = timeit.Timer(
            lambda r=robot, q=q0: (pin.crba(r.model, r.data, q), pin.cholesky.decompose(r.model, r.data)),
            timer=time.process_time,
        )
        factor = min(timer.repeat(repeat=5, number=200)) / 200
        D = robot.damping
        eig = np.linalg.eigvals(np.linalg.solve(M, np.diag(D))).real
        print(f"\ntalos {'with' if damped else 'without'} the URDF's damping: largest eigenvalue of M⁻¹D "
              f"{eig.max():.0f} /s; native dp54 CPU per evaluation (whole run) {per_eval * 1e6:.1f} µs; "
              f"CRBA + Cholesky {factor * 1e6:.1f} µs")  # fmt: skip
        best: dict[tuple[str, float], tuple[float, int]] = {}
        for tol in tolerances:
            for name in METHODS:
                samples, evaluations, steps, factorizations = run(robot, q0, v0, name, tol, args.duration)
                error = max(max(np.max(abs(robot.space.difference(Qk, q))), np.max(abs(v - Vk)))
                            for (q, v), Qk, Vk in zip(samples, Q, V, strict=True))  # fmt: skip
                cost = evaluations * per_eval + factorizations * factor
                print(f"  {name:9s} tol {tol:.2e}: error {error:.2e}, {evaluations:5d} evaluations, {steps:4d} steps, "
                      f"estimated native CPU {cost * 1e3:5.1f} ms")  # fmt: skip
                for accuracy in ACCURACIES:
                    if error <= accuracy and cost < best.get((name, accuracy), (math.inf, 0))[0]:
                        best[(name, accuracy)] = (cost, evaluations)
        for accuracy in ACCURACIES:
            cells = [f"{name} {best[(name, accuracy)][1]} ev / {best[(name, accuracy)][0] * 1e3:.1f} ms"
                     if (name, accuracy) in best else f"{name} —" for name in METHODS]  # fmt: skip
            print(f"  cheapest to {accuracy:.0e}: " + "; ".join(cells))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
