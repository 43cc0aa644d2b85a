"""The filters' compiled kernels: :func:`torchcontact._compiled.kernel` (one compile cache per
process, shared with the simulator)."""

from torchcontact._compiled import kernel

__all__ = ["kernel"]
