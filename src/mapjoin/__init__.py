"""mapjoin: join 2D point-feature local maps into one global map, fast and certified.

Implements the spherical-covariance one-step solver of Wang, Huang, Frese and
Dissanayake, "The nonlinearity structure of point feature SLAM problems with spherical
covariance matrices", Automatica 49 (2013) 3112-3119 (docs/method.md), and the exact
least-squares join it approximates.

The public API (everything in ``__all__``; each name is imported the first time it is
used, so ``import mapjoin`` stays cheap and scipy is loaded only by :func:`refine`)::

    import mapjoin

    maps = mapjoin.read_maps("../shared/data/VicPark_200_local_maps")  # a path, a glob, "-" or a list
    fast = mapjoin.join(maps)                          # sequential one-step joins (strategy="tree" too)
    fast.report[0].minima                              # each join's certificate: 1 or 2 local minima
    fast.report[0].p                                   # its chi-square check (chi2, dof, p, flag)
    mapjoin.join(maps, gate=1e-10, on_inconsistent="stop")  # or "warn" (default), "skip"
    mapjoin.join(maps, confirm=mapjoin.confirm)       # failing joins confirmed on the exact problem
    exact = mapjoin.join_and_refine(maps)              # the fast join, then the exact optimum
    mapjoin.write_global_map(exact.global_map, "exact.csv")
    mapjoin.check_minima(a=5.0, c_phi=2.5)             # Theorem 2 for one join's (a, C_phi)
    found = mapjoin.join_associated(maps_with_local_ids)  # feature ids local to each map: data association

Data: :class:`LocalMap` (a map in the frame of its start pose), :class:`GlobalMap`,
:class:`GroundTruth`. Errors: :class:`MapjoinError` and its subclasses :class:`InputError`
(a file or value that does not hold what is expected; the message names the source, the
line or field and the value) and :class:`JoinError` (maps that cannot be joined).
"""

from __future__ import annotations

import importlib
import sys
import types
from typing import Any

from .errors import InputError, JoinError, MapjoinError

# public name -> (module, attribute): imported on first use
_LAZY: dict[str, tuple[str, str]] = {
    "LocalMap": ("maps", "LocalMap"),
    "GlobalMap": ("maps", "GlobalMap"),
    "GroundTruth": ("maps", "GroundTruth"),
    "Provenance": ("maps", "Provenance"),
    "COVARIANCE_MODES": ("covariance", "COVARIANCE_MODES"),
    "spherical_variances": ("covariance", "spherical_variances"),
    "read_maps": ("io", "read_maps"),
    "iter_maps": ("io", "iter_maps"),
    "write_maps": ("io", "write_maps"),
    "read_global_map": ("io", "read_global_map"),
    "write_global_map": ("io", "write_global_map"),
    "write_trajectory": ("io", "write_trajectory"),
    "read_truth": ("io", "read_truth"),
    "write_truth": ("io", "write_truth"),
    "join": ("joining", "join"),
    "confirm": ("confirmation", "confirm"),
    "join_stream": ("streaming", "join_stream"),
    "join_associated": ("association", "join_associated"),
    "local_ids": ("association", "local_ids"),
    "JoinResult": ("joining", "JoinResult"),
    "JoinRecord": ("joining", "JoinRecord"),
    "check_minima": ("onestep", "summarise_minima"),
    "certify_pair": ("joining", "certify_pair"),
    "merge": ("merging", "merge"),
    "MergeResult": ("merging", "MergeResult"),
    "refine": ("refine", "refine"),
    "join_and_refine": ("refine", "join_and_refine"),
    "RefineResult": ("refine", "RefineResult"),
    "simulate": ("simulation", "simulate"),
    "simulate_stream": ("simulation", "simulate_stream"),
    "evaluate": ("evaluation", "evaluate"),
    "compare": ("evaluation", "compare"),
}

__all__ = ["InputError", "JoinError", "MapjoinError", "__version__", *_LAZY]


def __getattr__(name: str) -> Any:
    """The public names, imported the first time they are asked for; ``__version__`` from the installed
    package's metadata (importing importlib.metadata costs more than mapjoin's own modules)."""
    if name == "__version__":
        from importlib.metadata import PackageNotFoundError, version

        from .distribution import DISTRIBUTION

        try:
            value = version(DISTRIBUTION)
        except PackageNotFoundError:  # running from a source tree that is not installed
            value = "0.0.0+unknown"
    elif name in _LAZY:
        module, attribute = _LAZY[name]
        value = getattr(importlib.import_module(f".{module}", __name__), attribute)
    else:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    if name not in _SHADOWED:
        globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))


# The public function refine shares its name with the package that holds it. Importing the package
# sets it as an attribute of this one; a data descriptor on this package's type wins over that
# attribute, so ``mapjoin.refine`` is always the function (``from mapjoin.refine import ...`` and
# ``import mapjoin.refine.solver`` still reach the modules through sys.modules).
_SHADOWED = ("refine",)


class _Package(types.ModuleType):
    """mapjoin's module type: the public function named like its package wins over the package."""


for _name in _SHADOWED:
    setattr(_Package, _name, property(lambda _self, name=_name: __getattr__(name), lambda _self, _value: None))
sys.modules[__name__].__class__ = _Package
