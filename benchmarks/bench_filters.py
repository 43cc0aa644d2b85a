"""Filter benchmarks: a batched Kalman step against a per-filter NumPy loop, and one RBPF step.

Run ``python benchmarks/bench_filters.py``. Prints a markdown table and writes
``benchmarks/results/bench_filters.json``. Single-threaded (``torch.set_num_threads(1)``), so
the numbers compare algorithms rather than core counts, and pinned to the CPU where a probe
loop runs fastest (``_timing.pin_to_quietest_cpu``: on a shared virtual machine one CPU can be
slower than another for minutes). Each time is the best of several repeats (the
least-disturbed run); the JSON also keeps the median. The contact model's settings (short
steps, where a second of contention spans all runs of one setting timed back to back) are
timed in interleaved rounds (:func:`interleaved_best_of`).

1. Kalman predict + update (with log-likelihood) of 10,000 independent filters, 6-dim state,
   3-dim measurement, shared model matrices, float64, all checked to give the same posterior
   and log-likelihood:

   * ``torchcontact``: ``kf_predict`` + ``kf_update`` on the whole batch;
   * ``torch-kf`` (https://github.com/raphaelreme/torch-kf): ``KalmanFilter.predict``,
     ``project`` (with the precision of ``S``), ``log_likelihood`` and ``update`` with the
     Joseph form, on the whole batch;
   * ``numpy batched``: the same equations on stacked arrays (``np.matmul``, ``np.linalg``);
   * ``FilterPy``: a ``filterpy.kalman.KalmanFilter`` per filter, ``predict()``,
     ``update(z)`` and its ``log_likelihood``, in a Python loop;
   * ``numpy loop``: FilterPy's equations (Joseph form, ``np.linalg.inv``) written out in the
     per-filter loop, without the library's bookkeeping.

   torch-kf and FilterPy are the ``bench`` extra (``pip install -e .[bench]``); without them
   their rows are left out with a note.

2. One step of the RBPF on a ``LinearSwitchingModel`` with K = 6 modes, 6-dim state, 3-dim
   measurement, N = 100 / 1,000 / 10,000 particles, float32 and float64, both proposals.

3. One step of the RBPF on the planar contact model (``PlanarContactModel``): a finger pushing
   a box (12 contact slots, the K modes seen in 32 training rollouts), vision pose measurement;
   the step includes the per-mode linearization of ``solve_mode`` at the belief mean (timed
   alone as well: it does not depend on N).

2 and 3 run with the eager kernels and with ``compiled=True`` (the particles' Kalman kernels
and the linearization through ``torch.compile``; the warm-up steps compile, so the times
exclude compilation, which takes minutes for all the settings here).

``--device cuda`` runs the torch rows on the GPU (the NumPy and FilterPy rows stay on the CPU;
the clock is read after ``torch.cuda.synchronize``); ``--particles``, ``--kernels eager``,
``--rounds`` and ``--out`` choose the settings and the results file; ``--quick`` is a small
smoke run (N = 100, 2 rounds).
"""

from __future__ import annotations

import argparse
import importlib.util
import itertools
import json
import math
import os
import platform
import statistics
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from _timing import (  # benchmarks/ is on sys.path when run as a script
    device_name,
    parse_device,
    parse_sizes,
    pin_to_quietest_cpu,
    synchronize,
)

from torchcontact.filters import (
    RBPF,
    Gaussian,
    KinematicControl,
    LinearSwitchingModel,
    PlanarContactModel,
    Proposal,
    RBPFBelief,
    collect_modes,
    empirical_transition,
    kf_predict,
    kf_update,
)
from torchcontact.sim import pushed_box_rollout, pushed_box_scene

RESULTS = Path(__file__).resolve().parent / "results" / "bench_filters.json"
N_STATE, N_OBS, N_FILTERS, N_MODES = 6, 3, 10_000, 6
TARGET_RBPF_MS = 2.0  # per step at N = 1,000, float32
TARGET_KF_SPEEDUP = 20.0  # over the per-filter loop
#: Rounds of the contact-model rows, timed interleaved (:func:`interleaved_best_of`).
CONTACT_REPEATS = 15


#: Where the torch rows run (``--device``); the clock waits for its queued work.
DEVICE = torch.device("cpu")


def best_of(fn: Callable[[], object], *, repeats: int, number: int) -> dict[str, float]:
    """Seconds per call over ``repeats`` runs of ``number`` calls each: best and median wall
    time, and best CPU time of this process (less sensitive to other load on the machine)."""
    fn()  # warm-up
    return _summary([_timed_run(fn, number) for _ in range(repeats)])


def _timed_run(fn: Callable[[], object], number: int) -> tuple[float, float]:
    """Wall and CPU seconds per call of ``number`` calls of ``fn`` (on a GPU, until its queued
    kernels are done)."""
    synchronize(DEVICE)
    start, start_cpu = time.perf_counter(), time.process_time()
    for _ in range(number):
        fn()
    synchronize(DEVICE)
    return (time.perf_counter() - start) / number, (time.process_time() - start_cpu) / number


def _summary(runs: Sequence[tuple[float, float]]) -> dict[str, float]:
    """Best and median wall time and best CPU time of :func:`_timed_run` results."""
    wall = [w for w, _ in runs]
    return {
        "best_s": min(wall),
        "median_s": statistics.median(wall),
        "best_cpu_s": min(c for _, c in runs),
    }


def interleaved_best_of(
    settings: Sequence[tuple[Callable[[], object], int]], *, rounds: int
) -> list[dict[str, float]]:
    """:func:`best_of` for several settings ``(fn, number)`` timed in turn: each of ``rounds``
    rounds times one untimed call, then ``number`` calls, of every setting.

    A slow phase of a shared machine (seconds of contention) then slows every setting a little
    instead of all runs of one: the best of a setting's runs is spread over the whole
    section's time, not over a fraction of a second.
    """
    runs: list[list[tuple[float, float]]] = [[] for _ in settings]
    for _ in range(rounds):
        for (fn, number), timed in zip(settings, runs, strict=True):
            fn()  # its buffers back in the caches after the other settings' runs
            timed.append(_timed_run(fn, number))
    return [_summary(timed) for timed in runs]


def kalman_model(rng: np.random.Generator) -> dict[str, np.ndarray]:
    dt = 0.05
    F = np.eye(N_STATE)
    F[:3, 3:] = dt * np.eye(3)  # constant velocity in 3-D
    A = rng.normal(size=(N_STATE, N_STATE)) * 0.05
    return {
        "F": F,
        "Q": A @ A.T + 1e-4 * np.eye(N_STATE),
        "H": np.hstack([np.eye(3), np.zeros((3, 3))]),
        "R": 0.01 * np.eye(N_OBS),
        "x": rng.normal(size=(N_FILTERS, N_STATE)),
        "P": np.tile(np.eye(N_STATE), (N_FILTERS, 1, 1)),
        "y": rng.normal(size=(N_FILTERS, N_OBS)),
    }


def numpy_loop_step(m: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """FilterPy's KalmanFilter.predict() + update() (Joseph form), one filter at a time."""
    F, Q, H, R = m["F"], m["Q"], m["H"], m["R"]
    eye = np.eye(N_STATE)
    xs, Ps, lls = np.empty_like(m["x"]), np.empty_like(m["P"]), np.empty(N_FILTERS)
    for i in range(N_FILTERS):
        x = F @ m["x"][i]
        P = F @ m["P"][i] @ F.T + Q
        y = m["y"][i] - H @ x
        PHT = P @ H.T
        S = H @ PHT + R
        SI = np.linalg.inv(S)
        K = PHT @ SI
        x = x + K @ y
        IKH = eye - K @ H
        P = IKH @ P @ IKH.T + K @ R @ K.T
        xs[i], Ps[i] = x, P
        lls[i] = -0.5 * (y @ SI @ y + np.linalg.slogdet(S)[1] + N_OBS * math.log(2 * math.pi))
    return xs, Ps, lls


def numpy_batched_step(m: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The same equations on stacked arrays."""
    F, Q, H, R = m["F"], m["Q"], m["H"], m["R"]
    x = m["x"] @ F.T
    P = F @ m["P"] @ F.T + Q
    y = m["y"] - x @ H.T
    PHT = P @ H.T
    S = H @ PHT + R
    K = np.linalg.solve(S, PHT.transpose(0, 2, 1)).transpose(0, 2, 1)
    x = x + np.einsum("bij,bj->bi", K, y)
    IKH = np.eye(N_STATE) - K @ H
    P = IKH @ P @ IKH.transpose(0, 2, 1) + K @ R @ K.transpose(0, 2, 1)
    quad = np.einsum("bi,bi->b", y, np.linalg.solve(S, y[..., None])[..., 0])
    lls = -0.5 * (quad + np.linalg.slogdet(S)[1] + N_OBS * math.log(2 * math.pi))
    return x, P, lls


def bench_kalman() -> list[dict[str, Any]]:
    m = kalman_model(np.random.default_rng(0))
    t = {k: torch.from_numpy(v).to(DEVICE) for k, v in m.items()}
    prior = Gaussian(t["x"], t["P"])

    def torch_step() -> tuple[Any, Any, Any]:
        predicted = kf_predict(prior, F=t["F"], Q=t["Q"])
        posterior, log_lik = kf_update(predicted, t["y"], H=t["H"], R=t["R"])
        return posterior.mean, posterior.cov, log_lik

    candidates: list[tuple[str, Callable[[], tuple[Any, Any, Any]], int]] = [
        ("torchcontact kf_predict + kf_update", torch_step, 10)
    ]
    if importlib.util.find_spec("torch_kf") is not None and DEVICE.type == "cpu":
        candidates.append(("torch-kf KalmanFilter", _torch_kf_step(m), 10))
    candidates.append(("numpy batched (stacked arrays)", lambda: numpy_batched_step(m), 5))
    if importlib.util.find_spec("filterpy") is not None:
        candidates.append(("FilterPy KalmanFilter per filter", _filterpy_step(m), 1))
    # last: the per-filter loop, the reference of the speed-ups
    reference = "numpy per-filter loop (FilterPy's equations)"
    candidates.append((reference, lambda: numpy_loop_step(m), 1))

    # the implementations agree
    x_ref, P_ref, ll_ref = numpy_loop_step(m)
    for name, fn, _ in candidates:
        for got, expected in zip(fn(), (x_ref, P_ref, ll_ref), strict=True):
            got = got.cpu().numpy() if isinstance(got, torch.Tensor) else np.asarray(got)
            assert np.allclose(got, expected, atol=1e-9), name

    rows = [
        {"name": name, **best_of(fn, repeats=5 if number > 1 else 2, number=number)}
        for name, fn, number in candidates
    ]
    for row in rows:
        row["speedup_vs_loop"] = rows[-1]["best_s"] / row["best_s"]
    return rows


def _torch_kf_step(m: dict[str, np.ndarray]) -> Callable[[], tuple[Any, Any, Any]]:
    """torch-kf, float64, same model: predict, project (precision of S precomputed, as its
    ``update`` uses it), log-likelihood of the measurement, Joseph-form update."""
    from torch_kf import GaussianState, KalmanFilter

    t = {k: torch.from_numpy(v) for k, v in m.items()}
    kf = KalmanFilter(t["F"], t["H"], t["Q"], t["R"], joseph_update=True)
    state = GaussianState(t["x"][..., None], t["P"])
    y = t["y"][..., None]

    def step() -> tuple[Any, Any, Any]:
        predicted = kf.predict(state)
        projection = kf.project(predicted)
        log_lik = projection.log_likelihood(y)
        posterior = kf.update(predicted, y, projection=projection)
        return posterior.mean[..., 0], posterior.covariance, log_lik

    return step


def _filterpy_step(m: dict[str, np.ndarray]) -> Callable[[], tuple[Any, Any, Any]]:
    """FilterPy: one ``KalmanFilter`` per filter (built once), each step from the prior."""
    from filterpy.kalman import KalmanFilter

    filters = []
    for _ in range(N_FILTERS):
        kf = KalmanFilter(dim_x=N_STATE, dim_z=N_OBS)
        kf.F, kf.Q, kf.H, kf.R = m["F"], m["Q"], m["H"], m["R"]
        filters.append(kf)
    x0, P0, ys = m["x"][..., None], m["P"], m["y"]

    def step() -> tuple[Any, Any, Any]:
        xs, Ps, lls = np.empty_like(m["x"]), np.empty_like(m["P"]), np.empty(N_FILTERS)
        for i, kf in enumerate(filters):
            kf.x, kf.P = x0[i].copy(), P0[i].copy()
            kf.predict()
            kf.update(ys[i])
            xs[i], Ps[i], lls[i] = kf.x[:, 0], kf.P, kf.log_likelihood
        return xs, Ps, lls

    return step


def switching_model(dtype: torch.dtype) -> LinearSwitchingModel:
    gen = torch.Generator().manual_seed(0)
    K, n, m = N_MODES, N_STATE, N_OBS
    skew = 0.1 * torch.randn(K, n, n, generator=gen, dtype=torch.float64)
    F = 0.99 * torch.linalg.matrix_exp(skew - skew.mT)  # stable, mode-specific rotations
    A = 0.1 * torch.randn(K, n, n, generator=gen, dtype=torch.float64)
    stay = 0.9
    transition = torch.full((K, K), (1 - stay) / (K - 1), dtype=torch.float64)
    transition.fill_diagonal_(stay)
    return LinearSwitchingModel(
        F=F,
        c=0.1 * torch.randn(K, n, generator=gen, dtype=torch.float64),
        Q=A @ A.mT + 0.01 * torch.eye(n, dtype=torch.float64),
        H=torch.randn(K, m, n, generator=gen, dtype=torch.float64),
        d=torch.zeros(K, m, dtype=torch.float64),
        R=0.1 * torch.eye(m, dtype=torch.float64).expand(K, m, m).clone(),
        transition=transition,
        initial=torch.full((K,), 1.0 / K, dtype=torch.float64),
    ).to(dtype)


def _stepper(
    rbpf: RBPF, belief: RBPFBelief, ys: torch.Tensor, gen: torch.Generator
) -> Callable[[], RBPFBelief]:
    """The filter running on: each call is one step, from the previous call's belief, on the
    next measurement (so ESS-triggered resampling happens at its natural rate)."""
    state = [belief]
    count = [0]

    def step() -> RBPFBelief:
        count[0] += 1
        state[0] = rbpf.step(state[0], ys[count[0] % len(ys)], generator=gen)
        return state[0]

    return step


def simulate(model: LinearSwitchingModel, steps: int) -> torch.Tensor:
    """Measurements ``(steps, m)`` drawn from the switching model itself."""
    gen = torch.Generator().manual_seed(1)
    mode = 0
    x = torch.zeros(model.state_dim, dtype=torch.float64)
    ys = []
    for _ in range(steps):
        mode = int(torch.multinomial(model.transition[mode].double(), 1, generator=gen))
        noise = torch.linalg.cholesky(model.Q[mode].double()) @ torch.randn(
            model.state_dim, generator=gen, dtype=torch.float64
        )
        x = model.F[mode].double() @ x + model.c[mode].double() + noise
        v = torch.linalg.cholesky(model.R[mode].double()) @ torch.randn(
            model.obs_dim, generator=gen, dtype=torch.float64
        )
        ys.append(model.H[mode].double() @ x + model.d[mode].double() + v)
    return torch.stack(ys)


def bench_rbpf(particle_counts: Sequence[int], kernels: Sequence[bool]) -> list[dict[str, Any]]:
    rows: list[dict[str, Any]] = []
    for dtype in (torch.float32, torch.float64):
        model = switching_model(dtype)
        ys = simulate(model, 64).to(dtype=dtype, device=DEVICE)
        model = model.to(DEVICE)
        prior = Gaussian(
            torch.zeros(N_STATE, dtype=dtype, device=DEVICE),
            torch.eye(N_STATE, dtype=dtype, device=DEVICE),
        )
        proposals: tuple[Proposal, ...] = ("bootstrap", "all_modes")
        for compiled, proposal in itertools.product(kernels, proposals):
            for particles in particle_counts:
                rbpf = RBPF(model, particles, proposal=proposal, compiled=compiled)
                gen = torch.Generator(DEVICE).manual_seed(0)
                belief = rbpf.init(prior)
                step = _stepper(rbpf, belief, ys, gen)
                for _ in range(10):  # settle: weights, resampling, allocator (and compile)
                    step()
                number = 20 if particles <= 1_000 else 4
                timing = best_of(step, repeats=5, number=number)
                rows.append(
                    {
                        "proposal": proposal,
                        "compiled": compiled,
                        "dtype": str(dtype).removeprefix("torch."),
                        "particles": particles,
                        **timing,
                    }
                )
    return rows


def bench_rbpf_contact(
    particle_counts: Sequence[int], kernels: Sequence[bool], rounds: int
) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    """RBPF steps on the pushed-box contact model; returns rows and the scene's facts."""
    scene = pushed_box_scene()
    steps = 60
    train, _ = pushed_box_rollout(scene, batch=32, steps=steps, seed=0)
    table, ids, _ = collect_modes(train.mode)
    K = len(table)
    truth, controls = pushed_box_rollout(scene, batch=1, steps=steps, seed=1)
    gen = torch.Generator().manual_seed(2)
    sigma = torch.tensor([0.005, 0.005, 0.02], dtype=torch.float64)
    ys = truth.q[1:, 0, 0] + sigma * torch.randn(steps, 3, generator=gen, dtype=torch.float64)
    # the trial on the device (the training rollouts ran on the CPU: only their modes are used)
    gen = torch.Generator(DEVICE).manual_seed(2)
    ys, sigma, table = ys.to(DEVICE), sigma.to(DEVICE), table.to(DEVICE)
    q_kinematic, controls = truth.q_kinematic.to(DEVICE), controls.to(DEVICE)
    rows: list[dict[str, Any]] = []
    settings: list[tuple[Callable[[], object], int]] = []
    for dtype, compiled in itertools.product((torch.float32, torch.float64), kernels):
        on = {"dtype": dtype, "device": DEVICE}
        model = PlanarContactModel(
            scene=scene,
            compiled=compiled,
            modes=table,
            Q=torch.diag(torch.tensor([1e-6] * 3 + [1e-4] * 3, **on)),
            R=torch.diag(sigma**2).to(dtype),
            transition=empirical_transition(ids, K, smoothing=0.1, dtype=dtype).to(DEVICE),
            initial=torch.full((K,), 1.0 / K, **on),
        )
        x0 = torch.tensor([0.0, 0.05, 0.0, 0.0, 0.0, 0.0], **on)
        prior = Gaussian(x0, torch.diag(torch.tensor([1e-4, 1e-6, 1e-4] + [1e-2] * 3, **on)))
        control = KinematicControl(q=q_kinematic[5, 0], v=controls[5, 0])
        kind = {"compiled": compiled, "dtype": str(dtype).removeprefix("torch.")}
        rows.append({"what": "linearize", **kind})
        settings.append((lambda m=model, x=x0, u=control: m.linearize(x, control=u), 5))
        proposals: tuple[Proposal, ...] = ("bootstrap", "all_modes")
        for proposal in proposals:
            for particles in particle_counts:
                rbpf = RBPF(model, particles, proposal=proposal, compiled=compiled)
                state = [rbpf.init(prior), 0]

                def step(rbpf: RBPF = rbpf, state: list[Any] = state) -> None:
                    t = state[1] % steps
                    state[0] = rbpf.step(
                        state[0],
                        ys[t].to(rbpf.model.dtype),
                        control=KinematicControl(q=q_kinematic[t, 0], v=controls[t, 0]),
                        generator=gen,
                    )
                    state[1] += 1

                for _ in range(5):  # settle (and compile)
                    step()
                rows.append({"what": proposal, **kind, "particles": particles})
                settings.append((step, 5 if particles <= 1_000 else 2))
    timings = interleaved_best_of(settings, rounds=rounds)
    rows = [row | timing for row, timing in zip(rows, timings, strict=True)]
    return rows, {"slots": scene.num_slots, "modes": K}


def _kernels(row: dict[str, Any]) -> str:
    return "compiled" if row["compiled"] else "eager"


def _speedup(row: dict[str, Any], rows: list[dict[str, Any]], kind: str) -> str:
    """Eager time over compiled time of the same setting, on the compiled rows."""
    if not row["compiled"]:
        return ""
    eager = next(
        r
        for r in rows
        if not r["compiled"]
        and all(r.get(key) == row.get(key) for key in (kind, "dtype", "particles"))
    )
    return f"{eager['best_s'] / row['best_s']:.2f}×"


def _target_ms(
    rows: list[dict[str, Any]], kind: str, *, compiled: bool, key: str = "best_s"
) -> float:
    """Milliseconds (``key``) of the targets' row (a bootstrap step, N = 1,000, float32); NaN
    if the settings left it out."""
    row = next(
        (
            r
            for r in rows
            if r[kind] == "bootstrap"
            and r["compiled"] == compiled
            and r["dtype"] == "float32"
            and r.get("particles") == 1_000
        ),
        None,
    )
    return math.nan if row is None else row[key] * 1e3


def _cpu_model() -> str:
    cpuinfo = Path("/proc/cpuinfo")
    if cpuinfo.exists():
        for line in cpuinfo.read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    return platform.processor() or platform.machine()


def machine() -> dict[str, Any]:
    return {
        "platform": platform.platform(),
        "cpu": _cpu_model(),
        "cpu_count": os.cpu_count(),
        "load_average_1min": os.getloadavg()[0] if hasattr(os, "getloadavg") else None,
        "python": platform.python_version(),
        "torch": torch.__version__,
        "numpy": np.__version__,
        "torch_threads": torch.get_num_threads(),
    }


def main() -> None:
    global DEVICE
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="small sizes, for smoke tests")
    parser.add_argument("--device", default="cpu", help="where the torch rows run (cuda)")
    parser.add_argument("--particles", help="comma-separated particle counts N of the RBPFs")
    parser.add_argument(
        "--kernels", choices=("both", "eager"), default="both", help="eager only: no compiling"
    )
    parser.add_argument("--rounds", type=int, help="rounds of the contact model's rows")
    parser.add_argument("--out", type=Path, default=RESULTS, help="the JSON results file")
    args = parser.parse_args()
    DEVICE = parse_device(args.device)
    default = (100,) if args.quick else (100, 1_000, 10_000)
    particle_counts = parse_sizes(args.particles) if args.particles else default
    kernels = (False,) if args.kernels == "eager" else (False, True)
    rounds = args.rounds or (2 if args.quick else CONTACT_REPEATS)
    torch.set_num_threads(1)
    pinned = pin_to_quietest_cpu()
    info = machine() | pinned | {"device": str(DEVICE), "device_name": device_name(DEVICE)}
    kalman = bench_kalman()
    rbpf = bench_rbpf(particle_counts, kernels)
    contact, contact_facts = bench_rbpf_contact(particle_counts, kernels, rounds)

    print(f"torch rows on {DEVICE}: {info['device_name']}\n")
    print(
        f"# bench_filters ({info['cpu']}, {info['cpu_count']} cores, 1-min load "
        f"{info['load_average_1min']:.1f}; torch {info['torch']}, 1 thread, pinned to CPU "
        f"{info['pinned_cpu']} of probe speeds {info['probe_ns']} ns)\n"
    )
    print(
        "Times are per step: best wall time of 5 runs (and best CPU time of this process); "
        f"the contact model's settings are timed in {rounds} interleaved rounds, each "
        "setting's run after one untimed step.\n"
    )
    print(
        f"## Kalman predict + update: {N_FILTERS:,} filters, n = {N_STATE}, m = {N_OBS}, float64\n"
    )
    print(
        "| implementation | wall (ms) | CPU (ms) | per filter (µs) | speed-up vs per-filter loop |"
        " torchcontact's speed-up over it |"
    )
    print("|---|---:|---:|---:|---:|---:|")
    ours = kalman[0]["best_s"]
    for row in kalman:
        print(
            f"| {row['name']} | {row['best_s'] * 1e3:.2f} | {row['best_cpu_s'] * 1e3:.2f} | "
            f"{row['best_s'] / N_FILTERS * 1e6:.3f} | {row['speedup_vs_loop']:.1f}× | "
            f"{row['best_s'] / ours:.2f}× |"
        )
    for package, name in (("torch_kf", "torch-kf"), ("filterpy", "FilterPy")):
        if importlib.util.find_spec(package) is None:
            print(f"\n({name} is not installed (the bench extra): not compared.)")

    print(f"\n## RBPF step: K = {N_MODES} modes, n = {N_STATE}, m = {N_OBS}\n")
    print(
        "| proposal | kernels | dtype | particles | wall (ms) | CPU (ms) | per particle (µs) |"
        " compiled vs eager |"
    )
    print("|---|---|---|---:|---:|---:|---:|---:|")
    for row in rbpf:
        particles = row["particles"]
        print(
            f"| {row['proposal']} | {_kernels(row)} | {row['dtype']} | {particles:,} | "
            f"{row['best_s'] * 1e3:.3f} | {row['best_cpu_s'] * 1e3:.3f} | "
            f"{row['best_s'] / particles * 1e6:.3f} | {_speedup(row, rbpf, 'proposal')} |"
        )

    print(
        f"\n## RBPF step on the planar contact model: a finger pushing a box, "
        f"{contact_facts['slots']} slots, K = {contact_facts['modes']} modes, n = 6, m = 3\n"
    )
    print("| step | kernels | dtype | particles | wall (ms) | CPU (ms) | compiled vs eager |")
    print("|---|---|---|---:|---:|---:|---:|")
    for row in contact:
        particles = f"{row['particles']:,}" if "particles" in row else "(any)"
        print(
            f"| {row['what']} | {_kernels(row)} | {row['dtype']} | {particles} | "
            f"{row['best_s'] * 1e3:.2f} | {row['best_cpu_s'] * 1e3:.2f} | "
            f"{_speedup(row, contact, 'what')} |"
        )

    rbpf_ms = _target_ms(rbpf, "proposal", compiled=False)
    rbpf_cpu_ms = _target_ms(rbpf, "proposal", compiled=False, key="best_cpu_s")
    kf_speedup = kalman[0]["speedup_vs_loop"]
    contact_ms = _target_ms(contact, "what", compiled=False)
    compiled_ms = _target_ms(contact, "what", compiled=True)
    targets = {
        "rbpf_contact_step_ms_N1000_float32": contact_ms,
        "rbpf_contact_compiled_step_ms_N1000_float32": compiled_ms,
        "rbpf_contact_target_met": any(ms <= TARGET_RBPF_MS for ms in (contact_ms, compiled_ms)),
        "rbpf_step_ms_N1000_float32": rbpf_ms,
        "rbpf_step_cpu_ms_N1000_float32": rbpf_cpu_ms,
        "rbpf_target_ms": TARGET_RBPF_MS,
        "rbpf_target_met": rbpf_ms <= TARGET_RBPF_MS,
        "kf_speedup_vs_loop": kf_speedup,
        "kf_target_speedup": TARGET_KF_SPEEDUP,
        "kf_target_met": kf_speedup >= TARGET_KF_SPEEDUP,
    }
    verdict = {True: "met", False: "MISSED"}
    print(
        f"\nTargets: RBPF bootstrap step, N = 1,000, float32: {rbpf_ms:.2f} ms wall "
        f"({rbpf_cpu_ms:.2f} ms CPU); target <= {TARGET_RBPF_MS} ms: "
        f"{verdict[bool(targets['rbpf_target_met'])]}. Batched KF: {kf_speedup:.0f}x the "
        f"per-filter loop; target >= {TARGET_KF_SPEEDUP:.0f}x: "
        f"{verdict[bool(targets['kf_target_met'])]}. RBPF on the contact model, N = 1,000, "
        f"float32: {contact_ms:.2f} ms eager, {compiled_ms:.2f} ms compiled; target <= "
        f"{TARGET_RBPF_MS} ms: {verdict[bool(targets['rbpf_contact_target_met'])]}."
    )
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(
        json.dumps(
            {
                "machine": info,
                "kalman": kalman,
                "rbpf": rbpf,
                "rbpf_contact": contact,
                "targets": targets,
            },
            indent=2,
        )
        + "\n"
    )
    print(f"\nwrote {args.out}")


if __name__ == "__main__":
    main()
