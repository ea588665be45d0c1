"""psonurbs: fit NURBS surfaces to 3D point clouds by particle swarm optimisation.

The package is built in layers, each folder using only those below it:

    geometry/   B-spline bases, the NURBS surface, control-net layouts: pure math
    fitting/    organise, parametrise, swarm, solve, polish, refine: the method (no files)
    formats/    cloud readers, output writers, CAD exports (no fitting)
    run/        batches and workers, the gate, the summary, scoring, plots, demo
    config.py, errors.py   the fit configuration and the user-facing exceptions

``psonurbs.fit_points(points, config)`` fits one cloud; ``psonurbs.NurbsSurface`` is the
surface type. Both are imported on first use, so ``import psonurbs`` stays light.
"""

__version__ = "0.1.0"

_LAZY = {"fit_points": "psonurbs.fitting.pipeline", "FitResult": "psonurbs.fitting.pipeline",
         "NurbsSurface": "psonurbs.geometry.nurbs", "FitConfig": "psonurbs.config",
         "load_config": "psonurbs.config", "read_cloud": "psonurbs.formats.clouds"}

__all__ = ["__version__", *_LAZY]


def __getattr__(name: str):
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'psonurbs' has no attribute {name!r}")
