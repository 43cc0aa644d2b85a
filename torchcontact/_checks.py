"""Input validation for every public entry point of the library.

One rule holds throughout: a bad argument (wrong type, shape, dtype or device, NaN or inf,
a value out of range) raises ``ValueError`` whose message starts with the argument's name.
No entry point raises ``TypeError`` for a wrong type: a caller catches one exception type.
"""

from __future__ import annotations

import json
import math
import numbers
import os
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path

import torch
from torch import Tensor

#: The floating dtypes the library computes in.
FLOAT_DTYPES = (torch.float32, torch.float64)


def describe(value: object) -> str:
    """A short description of a value for error messages: dtype and shape of a tensor."""
    if isinstance(value, Tensor):
        return f"a {value.dtype} tensor of shape {tuple(value.shape)}"
    return type(value).__name__


def all_finite(value: Tensor) -> bool:
    """Whether every entry of a floating tensor is finite.

    A finite sum proves it (NaN and ±inf propagate through a sum) and costs far less than an
    elementwise test on large tensors; only a non-finite sum (a non-finite entry, or an
    overflow) falls back to the elementwise test. Inside a region that :func:`torch.compile`
    traces it answers True without looking (a host synchronisation would split the graph):
    compiled hot paths check their inputs where they enter, before the compiled region.
    """
    if torch.compiler.is_compiling():
        return True
    if bool(torch.isfinite(value.sum())):
        return True
    return bool(torch.isfinite(value).all())


def check_int(name: str, value: object, *, low: int, high: int | None = None, why: str = "") -> int:
    """Check that ``value`` is an integer (not a bool) in ``[low, high)`` and return it.

    ``numpy`` integers are accepted and converted to ``int``; ``high=None`` means no upper
    bound.

    Args:
        name: the argument's name, used in the error message.
        value: the object to check.
        low: the least allowed value.
        high: one past the largest allowed value (``None``: no upper bound).
        why: where the bounds come from, shown in parentheses (empty: nothing).

    Raises:
        ValueError: ``value`` is not an integer or lies outside the range.
    """
    if not isinstance(value, bool) and isinstance(value, numbers.Integral):
        result = int(value)
        if result >= low and (high is None or result < high):
            return result
    bounds = f"in [{low}, {high})" if high is not None else f">= {low}"
    reason = f" ({why})" if why else ""
    raise ValueError(f"{name}: expected an int {bounds}{reason}, got {value!r}")


def check_real(
    name: str,
    value: object,
    *,
    low: float = -math.inf,
    high: float = math.inf,
    low_open: bool = False,
    high_open: bool = False,
) -> float:
    """Check that ``value`` is a finite real number in the given interval and return it.

    Args:
        name: the argument's name, used in the error message.
        value: the object to check (a Python or numpy real number, not a bool).
        low: lower bound.
        high: upper bound.
        low_open: exclude ``low`` itself.
        high_open: exclude ``high`` itself.

    Raises:
        ValueError: ``value`` is not a finite real number in the interval.
    """
    if not isinstance(value, bool) and isinstance(value, numbers.Real):
        result = float(value)
        above = result > low if low_open else result >= low
        below = result < high if high_open else result <= high
        if math.isfinite(result) and above and below:
            return result
    if high == math.inf:
        bound = f"{'>' if low_open else '>='} {low:g}"
        raise ValueError(f"{name}: expected a finite number {bound}, got {value!r}")
    interval = f"{'(' if low_open else '['}{low}, {high}{')' if high_open else ']'}"
    raise ValueError(f"{name}: expected a finite number in {interval}, got {value!r}")


def check_positive(name: str, value: object) -> float:
    """Check that ``value`` is a finite real number ``> 0`` and return it as a float.

    Raises:
        ValueError: ``value`` is not a finite positive number.
    """
    return check_real(name, value, low=0.0, low_open=True)


def check_trailing(name: str, value: Tensor, *, trailing: Sequence[int], what: str) -> None:
    """Check the trailing sizes of ``value`` (``-1`` in ``trailing`` accepts any size).

    Raises:
        ValueError: ``value`` has too few dimensions or a trailing size differs.
    """
    k = len(trailing)
    tail = tuple(value.shape[value.ndim - k :]) if value.ndim >= k else None
    if tail is None or any(t not in (-1, s) for t, s in zip(trailing, tail, strict=True)):
        raise ValueError(f"{name} must have shape {what}, got {tuple(value.shape)}")


def check_float(
    name: str,
    value: object,
    *,
    trailing: Sequence[int] = (),
    min_ndim: int = 0,
    what: str = "",
) -> Tensor:
    """Check that ``value`` is a finite float32/float64 tensor of the described shape.

    Args:
        name: the argument's name, used in the error message.
        value: the object to check.
        trailing: required trailing sizes; ``-1`` accepts any size.
        min_ndim: the least number of dimensions.
        what: human description of the expected shape, e.g. ``"(*B, K, d)"``.

    Returns:
        ``value``, typed as a tensor.

    Raises:
        ValueError: ``value`` is not a float32/float64 tensor, has the wrong shape, or holds
            NaN or inf.
    """
    if not isinstance(value, Tensor):
        raise ValueError(f"{name} must be a torch.Tensor, got {type(value).__name__}")
    if value.dtype not in FLOAT_DTYPES:
        raise ValueError(f"{name} must be float32 or float64, got dtype {value.dtype}")
    if value.ndim < min_ndim:
        raise ValueError(f"{name} must have shape {what}, got {tuple(value.shape)}")
    check_trailing(name, value, trailing=trailing, what=what)
    if value.numel() and not all_finite(value):
        raise ValueError(f"{name} contains NaN or inf")
    return value


def check_tensor(
    name: str,
    x: object,
    *,
    event_shape: Sequence[int],
    like: Tensor,
    allow_nan: bool = False,
    allow_neginf: bool = False,
) -> Tensor:
    """Check that ``x`` is a finite ``(*B', *event_shape)`` tensor with ``like``'s dtype/device.

    Args:
        name: argument name used in error messages.
        x: the value to check.
        event_shape: required trailing shape.
        like: reference tensor giving dtype and device.
        allow_nan: let NaN through (the caller gives it a meaning).
        allow_neginf: let ``-inf`` through (a log-probability of zero); ``+inf`` is an error.

    Returns:
        ``x`` as a tensor.
    """
    if not isinstance(x, Tensor):
        raise ValueError(f"{name}: expected a torch.Tensor, got {type(x).__name__}")
    if x.dtype != like.dtype or x.device != like.device:
        raise ValueError(
            f"{name}: expected dtype {like.dtype} on {like.device}, got {x.dtype} on {x.device}"
        )
    event = tuple(event_shape)
    if x.ndim < len(event) or tuple(x.shape[x.ndim - len(event) :]) != event:
        shape = ", ".join(["*B", *map(str, event)])
        raise ValueError(f"{name}: expected shape ({shape}), got {tuple(x.shape)}")
    if allow_nan:
        bad = torch.isposinf(x) if allow_neginf else torch.isinf(x)
    else:
        bad = torch.isposinf(x) | torch.isnan(x) if allow_neginf else ~torch.isfinite(x)
    if bool(bad.any()):
        allowed = " or ".join(["NaN"] * (not allow_nan) + ["-inf"] * (not allow_neginf) + ["+inf"])
        raise ValueError(f"{name}: contains {allowed}")
    return x


def check_like(name: str, value: Tensor, *, reference_name: str, reference: Tensor) -> None:
    """Check that ``value`` has the dtype and device of ``reference`` (nothing is cast silently).

    Raises:
        ValueError: The dtypes or devices differ.
    """
    if value.dtype != reference.dtype or value.device != reference.device:
        raise ValueError(
            f"{name} must have the dtype and device of {reference_name} "
            f"({reference.dtype}, {reference.device}), got ({value.dtype}, {value.device})"
        )


def check_dtype(name: str, value: object, dtype: torch.dtype, what: str) -> Tensor:
    """Check that ``value`` is a tensor of exactly ``dtype`` (``what`` describes its shape).

    Raises:
        ValueError: ``value`` is not a tensor of that dtype.
    """
    if not isinstance(value, Tensor) or value.dtype != dtype:
        got = value.dtype if isinstance(value, Tensor) else type(value).__name__
        raise ValueError(f"{name} must be a {dtype} tensor {what}, got {got}")
    return value


def check_mask(name: str, mask: object, *, size: int) -> Tensor:
    """Check that ``mask`` is a ``(*B', size)`` bool tensor."""
    if not isinstance(mask, Tensor) or mask.dtype != torch.bool:
        raise ValueError(f"{name}: expected a bool tensor, got {getattr(mask, 'dtype', mask)!r}")
    if mask.ndim < 1 or mask.shape[-1] != size:
        raise ValueError(f"{name}: expected shape (*B, {size}), got {tuple(mask.shape)}")
    return mask


def check_unit_rows(name: str, value: Tensor) -> None:
    """Check that every vector along the last dimension of ``value`` has unit length.

    The tolerance is 1e-6 in float64 and 1e-3 in float32 (on the length). Skipped inside a
    region that :func:`torch.compile` traces (see :func:`all_finite`).

    Raises:
        ValueError: Some vector's length differs from 1 by more than the tolerance.
    """
    if torch.compiler.is_compiling():
        return
    tol = 1e-6 if value.dtype == torch.float64 else 1e-3
    error = (torch.linalg.vector_norm(value, dim=-1) - 1.0).abs()
    if error.numel() > 0 and float(error.max()) > tol:
        raise ValueError(
            f"{name} must hold unit vectors along its last dimension "
            f"(largest length error {float(error.max()):.3g} > {tol:g})"
        )


def check_dim(name: str, value: object) -> int:
    """Check that ``value`` is the spatial dimension 2 (planar) or 3 (spatial).

    Raises:
        ValueError: ``value`` is neither 2 nor 3.
    """
    if isinstance(value, bool) or value not in (2, 3):
        raise ValueError(f"{name} must be 2 (planar) or 3 (spatial), got {value!r}")
    assert isinstance(value, int)
    return value


def broadcast_batch(shapes: Sequence[tuple[str, Sequence[int]]]) -> torch.Size:
    """Broadcast named batch shapes (NumPy rules), naming every argument on failure.

    Plain Python: ``torch.broadcast_shapes`` costs tens of microseconds per call.

    Args:
        shapes: ``(argument name, batch shape)`` pairs.

    Returns:
        The broadcast batch shape.

    Raises:
        ValueError: the batch shapes do not broadcast; the message lists every argument's.
    """
    batch: list[int] = []
    for name, shape in shapes:
        dims = list(shape)
        if len(dims) > len(batch):
            batch = [1] * (len(dims) - len(batch)) + batch
        offset = len(batch) - len(dims)
        for i, size in enumerate(dims):
            current = batch[offset + i]
            if size != current and 1 not in (size, current):
                listing = ", ".join(f"{n} {tuple(s)}" for n, s in shapes)
                raise ValueError(
                    f"{name}: batch shape {tuple(dims)} does not broadcast with {tuple(batch)} "
                    f"(batch shapes do not broadcast: {listing})"
                )
            batch[offset + i] = current if size == 1 else size
    return torch.Size(batch)


def check_choice(name: str, value: object, choices: Iterable[str]) -> str:
    """Check that ``value`` is one of ``choices`` and return it.

    Raises:
        ValueError: ``value`` is not one of ``choices``.
    """
    allowed = tuple(choices)
    if value not in allowed:
        raise ValueError(f"{name}: expected one of {allowed}, got {value!r}")
    return str(value)


def check_name(name: str, value: object) -> str:
    """Check that ``value`` is a non-empty folder name (no path separator) and return it.

    Raises:
        ValueError: ``value`` is empty or holds ``/`` or ``\\``.
    """
    if not isinstance(value, str) or not value or "/" in value or "\\" in value:
        raise ValueError(f"{name}: expected a non-empty name without '/' or '\\', got {value!r}")
    return value


def check_field(name: str, data: object, key: str) -> object:
    """The entry ``key`` of the mapping ``data`` (a loaded file or state dict) named ``name``.

    Raises:
        ValueError: ``data`` is not a mapping or has no entry ``key``.
    """
    if not isinstance(data, Mapping):
        raise ValueError(f"{name} must be a mapping, got {type(data).__name__}")
    if key not in data:
        raise ValueError(f"{name} is missing the entry {key!r}")
    return data[key]


def check_generator_state(name: str, value: object) -> Tensor:
    """Check that ``value`` is a state that a CPU ``torch.Generator`` can load.

    Raises:
        ValueError: ``value`` is not a ``torch.uint8`` tensor of a CPU generator's state size.
    """
    value = check_dtype(name, value, torch.uint8, "(a CPU torch.Generator state)")
    try:
        torch.Generator().set_state(value)
    except RuntimeError as error:
        raise ValueError(f"{name} is not a CPU torch.Generator state ({error})") from None
    return value


def read_text_file(name: str, path: object) -> str:
    """The UTF-8 text of the file at ``path``.

    Raises:
        ValueError: ``path`` is not a str or ``os.PathLike``, or names no readable UTF-8 text
            file (missing, a directory, unreadable or not UTF-8).
    """
    if not isinstance(path, (str, os.PathLike)):
        raise ValueError(f"{name} must be a str or os.PathLike path, got {type(path).__name__}")
    try:
        return Path(path).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as error:
        raise ValueError(
            f"{name} {str(path)!r} cannot be read as a UTF-8 text file ({error})"
        ) from None


def check_instance(name: str, value: object, kind: type) -> None:
    """Check that ``value`` is an instance of ``kind``.

    Raises:
        ValueError: it is not (the message names ``kind`` and the type found).
    """
    if not isinstance(value, kind):
        raise ValueError(f"{name} must be a {kind.__name__}, got {type(value).__name__}")


def check_batched(
    name: str, value: object, *, shape: Sequence[int], like: Tensor, like_name: str
) -> Tensor:
    """Check that ``value`` is a finite float tensor of exactly ``shape``, dtype/device of ``like``.

    Args:
        name: the argument's name, used in the error message.
        value: the object to check.
        shape: the full required shape (batch dimensions included).
        like: reference tensor giving dtype and device.
        like_name: the reference's argument name, for the message.

    Raises:
        ValueError: ``value`` is not a float32/float64 tensor of that shape, dtype and device,
            or holds NaN or inf.
    """
    tensor = check_float(name, value)
    check_like(name, tensor, reference_name=like_name, reference=like)
    if tuple(tensor.shape) != tuple(shape):
        raise ValueError(f"{name} must have shape {tuple(shape)}, got {tuple(tensor.shape)}")
    return tensor


def symmetric_tolerance(value: Tensor) -> Tensor:
    """The absolute tolerance of :func:`check_symmetric_psd` for each ``(n, n)`` matrix.

    ``8 · n · eps · max|A_ij|`` per matrix, ``eps`` the dtype's machine epsilon: each entry
    of a covariance computed in floating point (``F P Fᵀ + Q``, a Gram matrix ``A Aᵀ``: sums
    of ``n`` products) carries a rounding error of up to about ``n · eps`` times the
    magnitude of its terms (Higham's ``γ_n`` bound), so mirror entries may differ, and a
    semi-definite matrix's smallest eigenvalue may come out negative, by a few times that
    much; relative to the matrix's own scale, so that the test does not depend on its units.
    The factor 8 also covers the backward error of the Cholesky factorization that tests
    definiteness.

    Args:
        value: ``(*B, n, n)`` floating tensor.

    Returns:
        ``(*B,)`` tolerances (0 for a zero matrix).
    """
    n = value.shape[-1]
    eps = torch.finfo(value.dtype).eps
    return value.detach().abs().amax(dim=(-2, -1)) * (8 * n * eps)


def check_symmetric_psd(name: str, value: Tensor, *, definite: bool = False) -> None:
    """Check that every ``(n, n)`` matrix of a finite ``value`` is symmetric positive
    semi-definite (positive definite if ``definite``), to :func:`symmetric_tolerance`.

    Symmetric: ``|A_ij - A_ji| <= tol``. Semi-definite: the Cholesky factorization of
    ``A + tol · I`` succeeds (every eigenvalue ``>= -tol``, up to the factorization's own
    rounding; a zero matrix passes). Definite: the Cholesky factorization of ``A`` itself
    succeeds (numerically positive definite). One host synchronization; only the failure
    path computes eigenvalues, for the message.

    Args:
        name: the argument's name, used in the error message.
        value: ``(*B, n, n)`` float32/float64 tensor without NaN or inf.
        definite: require positive definite rather than semi-definite.

    Raises:
        ValueError: some matrix is not symmetric, or not positive (semi-)definite; the message
            gives the worst matrix's batch index and its asymmetry or smallest eigenvalue.
    """
    if value.numel() == 0:
        return
    a = value.detach()
    n = a.shape[-1]
    tol = symmetric_tolerance(a)
    asymmetric = (a - a.mT).abs().amax(dim=(-2, -1)) > tol
    if n == 1:  # a scalar variance: no factorization needed
        indefinite = a[..., 0, 0] <= 0 if definite else a[..., 0, 0] < -tol
    elif definite:
        indefinite = torch.linalg.cholesky_ex(a).info != 0
    else:
        shift = (tol + torch.finfo(a.dtype).tiny)[..., None, None]
        eye = torch.eye(n, dtype=a.dtype, device=a.device)
        indefinite = torch.linalg.cholesky_ex(a + shift * eye).info != 0
    if not bool((asymmetric | indefinite).any()):
        return
    if bool(asymmetric.any()):
        index = _worst((a - a.mT).abs().amax(dim=(-2, -1)) - tol)
        asym = float((a - a.mT).abs()[index].max())
        raise ValueError(
            f"{name}: must be symmetric (|A - Aᵀ| <= 8·n·eps·max|A|), got a matrix with "
            f"|A - Aᵀ| = {asym:.3g} > {float(tol[index]):.3g}{_at(index)}"
        )
    eig = torch.linalg.eigvalsh(a).amin(-1)
    index = _worst(-eig if definite else -(eig + tol))
    rule = "positive definite" if definite else "positive semi-definite (eigenvalues >= -tol)"
    raise ValueError(
        f"{name}: must be symmetric {rule}, got a matrix with smallest eigenvalue "
        f"{float(eig[index]):.3g}{_at(index)}"
    )


def _worst(score: Tensor) -> tuple[int, ...]:
    """The batch index of the largest entry of ``score (*B)``."""
    return tuple(int(i) for i in torch.unravel_index(score.argmax(), score.shape))


def _at(index: tuple[int, ...]) -> str:
    """`` at batch index (i, j)`` for a batched value, empty for one matrix."""
    return f" at batch index {index}" if index else ""


def all_finite_many(*values: Tensor) -> bool:
    """Whether every entry of several floating tensors is finite, with one host
    synchronization: the sum of their sums is finite exactly when no entry is NaN or inf,
    unless finite sums overflow, when each tensor is tested by :func:`all_finite`."""
    sums = [value.detach().sum() for value in values if value.numel()]
    if not sums:
        return True
    total = sums[0]
    for partial in sums[1:]:
        total = total + partial
    if bool(torch.isfinite(total)):
        return True
    return all(all_finite(value.detach()) for value in values if value.numel())


def check_float_shape(name: str, value: object, *, trailing: Sequence[int], what: str) -> Tensor:
    """Check that ``value`` is a float32/float64 tensor with the given trailing sizes
    (``-1`` accepts any), without reading its values: usable under ``torch.func`` transforms
    (``vmap``, ``jacfwd``), where a test of the values would need a host synchronization.

    Raises:
        ValueError: ``value`` is not a float32/float64 tensor or its trailing sizes differ.
    """
    if not isinstance(value, Tensor) or value.dtype not in FLOAT_DTYPES:
        raise ValueError(f"{name}: expected a float32 or float64 tensor, got {describe(value)}")
    check_trailing(name, value, trailing=trailing, what=what)
    return value


def parse_json(name: str, text: object) -> object:
    """Parse ``text`` (a JSON document in a ``str`` or UTF-8 bytes) and return the value.

    Raises:
        ValueError: ``text`` is not a string or not valid JSON; the message names ``name``.
    """
    if not isinstance(text, (str, bytes, bytearray)):
        raise ValueError(f"{name} must be a JSON str, got {type(text).__name__}")
    try:
        return json.loads(text)
    except ValueError as error:  # JSONDecodeError and UnicodeDecodeError
        raise ValueError(f"{name} is not valid JSON ({error})") from None
