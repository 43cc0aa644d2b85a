"""torchcontact: contact-aware estimation, learning and execution for robotic manipulation."""

from torchcontact import contact, envs, filters, geometry, rl, robots, sim, states

__all__ = ["__version__", "contact", "envs", "filters", "geometry", "rl", "robots", "sim", "states"]

__version__ = "0.1.0"
