"""torchcontact: contact-aware estimation, learning and execution for robotic manipulation."""

from torchcontact import contact

__all__ = ["__version__", "contact"]

__version__ = "0.1.0"
