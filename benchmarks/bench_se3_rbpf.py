"""SE(3) contact RBPF benchmark: one trial of the BarrettHand box grasp, eager against compiled.

Run ``python benchmarks/bench_se3_rbpf.py``. Prints a markdown table and writes
``benchmarks/results/bench_se3_rbpf.json``. Single-threaded (``torch.set_num_threads(1)``) and
pinned to the CPU where a probe loop runs fastest (``_timing.pin_to_quietest_cpu``).

The filter is the experiment's (:func:`~torchcontact.experiments.box_contact_model` on its
16 simulated training trials at its default seed, the modes restricted to the first ``K`` it
collects, ``all``: every one, a uniform transition), all-modes proposal, ``N`` particles, the
pads' per-mode evidence; one trial of ``--steps`` steps of h = 10 ms (the issue's real-time
target: at most 10 ms per step with N = 1,000). Two variants are stepped in lockstep on the
same trial, so that the machine's load falls on both alike:

* ``eager``: ``SpatialContactModel(compiled=False)``, ``RBPF(compiled=False)``;
* ``compiled``: ``SpatialContactModel(compiled=True)`` (the linearization's contact assembly
  as a :func:`torch.compile` graph and its backward) and ``RBPF(compiled=True)`` (the
  particles' Kalman kernels). Its first steps compile (minutes on a CPU; Inductor caches the
  code on disk, so a later process compiles in seconds to a minute): reported apart, as
  ``first_steps_s``. The model compiles the assembly again at the first step whose number of
  solved modes passes a power of two (its graphs have static shapes): at most
  log2(K) + 1 graphs, the later ones inside the timed steps (the medians leave them out).

Per step, the CPU time of this thread (``time.thread_time``) of ``RBPF.step`` and, apart, of
the model's ``mode_dynamics`` (the linearization, included in the step); medians over the
steps after the first ``WARMUP``, and the steps' 90th percentile (the linearization
differentiates the solved modes only: one in the approach's steps, the first 30 of this
trial, more once the fingers touch). The mixture means of the two variants are compared at
every step (they agree to rounding: the compiled kernels sum in another order).

``--eager``: the eager variant alone (no compilation). ``--quick``: a small eager-only run
(``K = 2``, ``N = 50``, 14 steps, 2 training trials) that checks the script.

``--device cuda``: the filter on the GPU (the training trials are simulated on the CPU, then
the model, the trial and the prior move); its times are wall times after
``torch.cuda.synchronize`` (the CPU time of the thread does not count the GPU's work).
``--particles 1000,10000`` steps several particle counts; ``--out`` names the results file.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import platform
import statistics
import time
from dataclasses import dataclass
from pathlib import Path

import torch
from _timing import (  # benchmarks/ is on sys.path when run as a script
    device_name,
    parse_device,
    parse_sizes,
    pin_to_quietest_cpu,
    synchronize,
)
from torch import Tensor

from torchcontact.experiments import (
    BarrettBoxGrasp,
    BoxTrials,
    box_contact_model,
    box_prior,
    box_trials,
    joint_motion,
)
from torchcontact.filters import RBPF, Gaussian, SpatialContactModel
from torchcontact.sim import Rollout
from torchcontact.states import TactileArray

RESULTS = Path(__file__).resolve().parent / "results" / "bench_se3_rbpf.json"
#: Steps left out of the medians (the compiled variant compiles in its first).
WARMUP = 3
#: The issue's target: ms per step at N = 1,000, one trial.
TARGET_MS = 10.0


@dataclass
class Variant:
    """One filter of the comparison and its per-step times."""

    name: str
    model: SpatialContactModel
    rbpf: RBPF
    step_s: list[float]
    dynamics_s: list[float]
    first_steps_s: float = 0.0


def restricted(model: SpatialContactModel, K: int, *, compiled: bool) -> SpatialContactModel:
    """``model`` with its first ``K`` modes, a uniform transition and ``compiled`` (its other
    settings kept)."""
    uniform = torch.full((K, K), 1.0 / K, dtype=model.Q.dtype)
    return dataclasses.replace(
        model, modes=model.modes[:K], transition=uniform, initial=None, compiled=compiled
    )


def _moved(value: object, device: torch.device) -> object:
    return value.to(device) if isinstance(value, Tensor) else value


def model_on(model: SpatialContactModel, device: torch.device) -> SpatialContactModel:
    """``model`` with its tensors (and its tactile arrays') on ``device``."""
    tactile = {
        name: TactileArray(
            **{f.name: _moved(getattr(pad, f.name), device) for f in dataclasses.fields(pad)}
        )
        for name, pad in model.tactile.items()
    }
    tensors = {
        f.name: getattr(model, f.name).to(device)
        for f in dataclasses.fields(model)
        if isinstance(getattr(model, f.name), Tensor)
    }
    return dataclasses.replace(model, tactile=tactile, **tensors)


def trials_on(trials: BoxTrials, device: torch.device) -> BoxTrials:
    """``trials`` with their tensors (and their rollout's) on ``device``."""
    truth = trials.truth
    moved = Rollout(
        **{f.name: _moved(getattr(truth, f.name), device) for f in dataclasses.fields(truth)}
    )
    fields = {
        f.name: _moved(getattr(trials, f.name), device)
        for f in dataclasses.fields(trials)
        if f.name != "truth"
    }
    return BoxTrials(truth=moved, **fields)


def run_modes(
    full: SpatialContactModel,
    trials: BoxTrials,
    K: int,
    N: int,
    steps: int,
    compiled: bool,
    device: torch.device,
) -> dict[str, object]:
    """Step the variants in lockstep over one trial; their timings and agreement."""
    names = ("eager", "compiled") if compiled else ("eager",)
    variants = []
    for name in names:
        model = model_on(restricted(full, K, compiled=name == "compiled"), device)
        rbpf = RBPF(model, N, proposal="all_modes", compiled=name == "compiled")
        variants.append(Variant(name, model, rbpf, [], []))
    prior = box_prior(trials, torch.Generator().manual_seed(0))  # drawn on the CPU
    prior = Gaussian(prior.mean.to(device), prior.cov.to(device))
    trials = trials_on(trials, device)
    beliefs = [v.rbpf.init(prior) for v in variants]
    generators = [torch.Generator(device).manual_seed(1) for _ in variants]
    # on a GPU the thread's CPU time leaves out the kernels: wall time after synchronizing
    clock = time.thread_time if device.type == "cpu" else time.perf_counter
    largest_gap = 0.0
    for t in range(steps):
        control = joint_motion(trials, t)
        for i, v in enumerate(variants):
            belief = beliefs[i]
            extra = v.model.tactile_log_likelihood(
                trials.readings[t], pose=belief.mean()[..., :7], control=control
            )
            synchronize(device)
            wall, start = time.perf_counter(), clock()
            beliefs[i] = v.rbpf.step(
                belief, trials.y[t], extra_log_likelihood=extra, control=control,
                generator=generators[i],
            )  # fmt: skip
            synchronize(device)
            v.step_s.append(clock() - start)
            if t < WARMUP:
                v.first_steps_s += time.perf_counter() - wall
            start = clock()
            v.model.mode_dynamics(belief, control)
            synchronize(device)
            v.dynamics_s.append(clock() - start)
        if len(variants) == 2:
            means = [b.mean()[..., :3] for b in beliefs]
            largest_gap = max(largest_gap, float((means[0] - means[1]).abs().max()))
    out: dict[str, object] = {"K": K, "N": N, "steps": steps}
    for v in variants:
        out[v.name] = {
            "step_ms": 1e3 * statistics.median(v.step_s[WARMUP:]),
            "step_p90_ms": 1e3 * statistics.quantiles(v.step_s[WARMUP:], n=10)[-1],
            "mode_dynamics_ms": 1e3 * statistics.median(v.dynamics_s[WARMUP:]),
            "first_steps_s": v.first_steps_s,
        }
    if len(variants) == 2:
        out["largest_mean_difference_m"] = largest_gap
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="small eager-only check")
    parser.add_argument("--modes", default="4,all", help="comma-separated K values, or all")
    parser.add_argument("--eager", action="store_true", help="the eager variant alone")
    parser.add_argument("--particles", default="1000", help="comma-separated particle counts")
    parser.add_argument("--steps", type=int, default=30)
    parser.add_argument("--device", default="cpu", help="where the filter runs (cuda)")
    parser.add_argument("--out", type=Path, default=RESULTS, help="the JSON results file")
    args = parser.parse_args()
    device = parse_device(args.device)
    torch.set_num_threads(1)
    machine = pin_to_quietest_cpu()
    Ns = (50,) if args.quick else parse_sizes(args.particles)
    steps = 14 if args.quick else args.steps
    # The experiment's training trials (train/barrett_box_grasp.py: 16, seed 10,000 + its
    # seed 0) and 80 steps; its modes merged by slot group (35).
    settings = BarrettBoxGrasp(trials=2 if args.quick else 16, steps=max(80, steps))
    train = box_trials(settings, seed=10_000)
    full = box_contact_model(settings, train)
    trial = train.subset(torch.tensor([0]))
    Ks = [2] if args.quick else [
        full.num_modes if k == "all" else int(k) for k in args.modes.split(",")
    ]  # fmt: skip
    if max(Ks) > full.num_modes:
        raise SystemExit(f"--modes: the training trials give {full.num_modes} modes")
    compiled = not (args.quick or args.eager)
    rows = [
        run_modes(full, trial, K, N, steps, compiled=compiled, device=device)
        for N in Ns
        for K in Ks
    ]
    cpu = platform.processor()
    if os.path.exists("/proc/cpuinfo"):
        with open("/proc/cpuinfo") as info:
            names = [line.split(":", 1)[1].strip() for line in info if "model name" in line]
        cpu = names[0] if names else cpu
    load = os.getloadavg() if hasattr(os, "getloadavg") else (math.nan,) * 3
    print(f"CPU: {cpu}, one thread, load average {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}")
    print(f"filter on {device}: {device_name(device)}")
    print(f"target: <= {TARGET_MS:g} ms per step at N = 1,000\n")
    print(
        "| K | N | variant | step ms | step p90 ms | mode_dynamics ms | first 3 steps s "
        "| step vs eager |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for row in rows:
        eager = row["eager"]["step_ms"]  # type: ignore[index]
        for name in ("eager", "compiled"):
            if name not in row:
                continue
            r = row[name]
            print(
                f"| {row['K']} | {row['N']} | {name} | {r['step_ms']:.1f} | "  # type: ignore[index]
                f"{r['step_p90_ms']:.1f} | "  # type: ignore[index]
                f"{r['mode_dynamics_ms']:.1f} | {r['first_steps_s']:.1f} | "  # type: ignore[index]
                f"{eager / r['step_ms']:.2f}x |"  # type: ignore[index]
            )
        if "largest_mean_difference_m" in row:
            print(
                f"|   |   | mean difference (m) | {row['largest_mean_difference_m']:.2e} | | | | |"
            )
    if not args.quick or args.out != RESULTS:
        record = {
            "cpu": cpu,
            "device": str(device),
            "device_name": device_name(device),
            "load_average": load,
            "torch": torch.__version__,
            "threads": 1,
            **machine,
            "rows": rows,
        }
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(record, indent=2) + "\n")


if __name__ == "__main__":
    main()
