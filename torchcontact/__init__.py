"""torchcontact: contact-aware estimation, learning and execution for robotic manipulation."""

from torchcontact import contact, filters, geometry, rl, robots, sim, states

__all__ = ["__version__", "contact", "filters", "geometry", "rl", "robots", "sim", "states"]

__version__ = "0.1.0"
