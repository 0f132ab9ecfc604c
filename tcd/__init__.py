"""tcd: Taichi Contact Dynamics for granular materials (rigid spheres, Moreau-Jean, NLGS)."""

__version__ = "0.1.0"
__all__ = ["init", "__version__"]


def init(arch: str = "cpu", precision: str = "f64", **kwargs) -> None:
    """Initialise the Taichi backend once: arch "cpu" or "gpu", precision "f64" or "f32"."""
    from .backend import init as _init   # importing taichi is slow: only when asked
    _init(arch, precision, **kwargs)
