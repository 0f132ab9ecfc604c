"""tcd: Taichi Contact Dynamics for granular materials (rigid spheres, Moreau-Jean, NLGS)."""

import os as _os

__version__ = "0.1.0"
__all__ = ["init", "__version__"]

if "HOME" not in _os.environ:
    # Taichi 1.7.4 aborts the process when it is imported without HOME (core.cpp,
    # get_repo_dir: "Assertion failure: home != nullptr"), as under a cron job, a service or
    # `env -i`: the user's home from the password database, else the temporary folder
    # (session 74's review)
    _home = _os.path.expanduser("~")
    if _home == "~":
        import tempfile as _tempfile
        _home = _tempfile.gettempdir()
    _os.environ["HOME"] = _home


def init(arch: str = "cpu", precision: str = "f64", **kwargs) -> None:
    """Initialise the Taichi backend once: arch "cpu" or "gpu", precision "f64" or "f32"."""
    from .backend import init as _init   # importing taichi is slow: only when asked
    _init(arch, precision, **kwargs)


# tcd.io, tcd.runner, tcd.walls... after a plain `import tcd`, as docs/scripting.md writes them
# (each imported when first named: most of them import taichi, which is slow to load)
def __getattr__(name: str):
    import importlib
    import pkgutil
    if not name.startswith("_") and name in {m.name for m in pkgutil.iter_modules(__path__)}:
        return importlib.import_module(f"{__name__}.{name}")
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
