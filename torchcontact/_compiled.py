"""Opt-in :func:`torch.compile` of the filters' and the simulator's per-step kernels
(``compiled=True``).

A step of the :class:`~torchcontact.filters.RBPF` on a contact model is about two thousand
small tensor operations: the unrolled 6 × 6 Kalman algebra of ``_linalg`` over the particles,
and the linearization of every contact mode at the belief's mean. On a CPU their cost is the
dispatch of each operation (microseconds), not the arithmetic. TorchInductor fuses the
elementwise chains into a few generated C++ loops, which removes most of that cost; the
batched LAPACK calls of the linearization stay library calls. The code that calls the loops
and allocates their buffers is generated in C++ as well (Inductor's ``cpp_wrapper``).

The spatial contact model's linearization (:class:`~torchcontact.filters.SpatialContactModel`
with ``compiled=True``) compiles the contact assembly of its tangent replicas (a robot's
forward kinematics, every slot's geometry) as one graph; AOTAutograd compiles its backward.
It has no host synchronisation inside: the checks skip themselves in a traced region (the
model validates at its public methods), data-dependent branches run masked. Its shapes are
static (``dynamic=False``): the replicas are those of the modes solved at the mean, padded to
the next power of two, so a filter compiles one graph per power it reaches (at most
``log2(P K) + 1`` for P points and K modes). It uses Inductor's Python wrapper, which
compiles this large graph faster. The mode solves stay eager: compiled,
the backward of their LU solves runs as triangular solves on full systems, slower than eager.

The simulator's kernel (:class:`~torchcontact.sim.Simulator` with ``compiled=True``) is a
planar step at given modes: some 600 small operations eagerly, one call compiled (and one
more on the entries whose modes the active set corrects). Its loops are compiled scalar
(``vectorize=False``): their innermost dimensions are a scene's slots and rows, and
Inductor's vectors along them, masked loads and stores of a few doubles through temporary
arrays, made the kernel 1.6 times slower at 1,024 scenes (the same results).

What it costs:

* the first call of a kernel compiles it: tens of seconds on a CPU (a C++ compiler must be on
  the machine); TorchInductor caches the generated code on disk, so another process with the
  same shapes takes seconds;
* a call with new shapes (particles, batch, dtype) or a new grad mode compiles again, the
  second time with dynamic sizes (``torch.compile(dynamic=None)``), which later sizes reuse;
* the results equal the eager kernels' to rounding, not to the bit (fused loops sum in
  another order): about 1e-6 relative in float32, 1e-14 in float64.

Each kernel is compiled once per process and shared by every filter, model and simulator that
asks; each of its variants (dtype, particle count below and above the sizes where the unrolled
algebra changes its summation, models with and without shared noise, the simulator's scenes
and numbers of active slots) is one entry of dynamo's cache for the kernel. Past
``torch._dynamo.config.recompile_limit`` entries (8 by default) dynamo runs new variants
eagerly, which a process with a few filters reaches (the benchmark's eight settings do): the
first compiled kernel raises the limit to :data:`RECOMPILE_LIMIT` for the process.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any, TypeVar, cast

import torch

_Kernel = TypeVar("_Kernel", bound=Callable[..., Any])

#: Variants of one kernel compiled before dynamo runs new ones eagerly (at least).
RECOMPILE_LIMIT = 64


@functools.cache
def _compile(
    fn: Callable[..., Any], cpp_wrapper: bool, dynamic: bool | None, vectorize: bool
) -> Callable[..., Any]:
    config = torch._dynamo.config
    config.recompile_limit = max(config.recompile_limit, RECOMPILE_LIMIT)
    # The C++ wrapper calls the generated kernels and library functions from C++ instead of
    # a generated Python function: ~0.2 ms less per call of the planar contact linearization
    # (its compilation takes about 1.7 times as long).
    options: dict[str, Any] = {"cpp_wrapper": cpp_wrapper}
    if not vectorize:
        # Inductor vectorizes a loop along its innermost dimension; where that is a few slots
        # or rows (2 to 16), each vector is a masked load or store through a temporary array,
        # slower than the scalar loop (the simulator's kernel: 1.6x at 1,024 scenes).
        options["cpp.simdlen"] = 1
    compiled = torch.compile(fn, dynamic=dynamic, options=options)

    @functools.wraps(fn)
    def call(*args: Any, **kwargs: Any) -> Any:
        # A view as an input makes the compiled code guard on its base's layout, which varies
        # between steps (a resampled belief is fresh, another a view of the previous one;
        # the model's fields are slices of a packed tensor): each variant would compile anew,
        # up to torch's limit, then run eagerly. Contiguous copies of the (small) views keep one
        # variant.
        return compiled(*map(_fresh, args), **{k: _fresh(v) for k, v in kwargs.items()})

    return call


def _fresh(value: Any) -> Any:
    """A contiguous copy of a tensor view (owning its memory), a dict of them with its views
    copied; anything else as it is."""
    if isinstance(value, dict):
        return {k: _fresh(v) for k, v in value.items()}
    if isinstance(value, torch.Tensor) and value._is_view():
        return value.clone(memory_format=torch.contiguous_format)
    return value


def kernel(
    fn: _Kernel,
    *,
    compiled: bool,
    cpp_wrapper: bool = True,
    dynamic: bool | None = None,
    vectorize: bool = True,
) -> _Kernel:
    """``fn`` itself, or its compiled form if ``compiled`` (one per process and options:
    ``cpp_wrapper``, Inductor's C++ wrapper or its Python wrapper, which compiles faster;
    ``dynamic``, :func:`torch.compile`'s: None compiles a second shape with dynamic sizes,
    False every shape anew; ``vectorize``, whether the CPU loops use SIMD vectors: scalar
    loops are faster where the innermost dimensions are a few slots or rows)."""
    return cast(_Kernel, _compile(fn, cpp_wrapper, dynamic, vectorize)) if compiled else fn
