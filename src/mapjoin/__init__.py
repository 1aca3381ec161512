"""mapjoin: join 2D point-feature local maps into a global map, fast.

Implements the spherical-covariance one-step solver of Wang, Huang, Frese and
Dissanayake, "The nonlinearity structure of point feature SLAM problems with spherical
covariance matrices", Automatica 49 (2013) 3112-3119.
"""

from .errors import InputError, JoinError, MapjoinError
from .covariance import COVARIANCE_MODES, spherical_variances
from .maps import GlobalMap, GroundTruth, LocalMap, Provenance

__all__ = [
    "COVARIANCE_MODES",
    "GlobalMap",
    "GroundTruth",
    "InputError",
    "JoinError",
    "LocalMap",
    "MapjoinError",
    "Provenance",
    "spherical_variances",
    "__version__",
]


def __getattr__(name: str) -> str:
    """``__version__``, looked up the first time it is asked for: importing importlib.metadata costs more
    than mapjoin's own modules."""
    if name != "__version__":
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    from importlib.metadata import PackageNotFoundError, version

    try:
        found = version("mapjoin")
    except PackageNotFoundError:  # running from a source tree that is not installed
        found = "0.0.0+unknown"
    globals()["__version__"] = found
    return found
