"""torchcontact: contact-aware estimation, learning and execution for robotic manipulation."""

from torchcontact import contact, robots

__all__ = ["__version__", "contact", "robots"]

__version__ = "0.1.0"
