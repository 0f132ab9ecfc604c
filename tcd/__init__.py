"""tcd: Taichi Contact Dynamics for granular materials (rigid spheres, Moreau-Jean, NLGS)."""
from .backend import init

__version__ = "0.1.0"
__all__ = ["init", "__version__"]
